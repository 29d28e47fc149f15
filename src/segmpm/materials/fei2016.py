"""Viscous–elastic–plastic granular model of Fei et al. 2016 as used in the seed (docs/model.md §1).

* Jiang–Liu elastic energy w_e = A I₁^{5/2} + C I₁^{1/2} I₂ with I₂ = ½ ε⁰:ε⁰, C = 5 q_φ² A
  (Jiang & Liu 2003; Sun et al. 2015);
  σ^e = −p_e 1 + C √I₁ ε⁰, p_e = 2.5 A I₁^{3/2} + ½ C I₂/√I₁ (seed Eq. 3 corrected).
* Objective (Jaumann) elastic predictor; I₁ = −ln J so the volumetric state cannot drift.
* Yield cap √I₂ ≤ r_c I₁/q_φ on the deviatoric elastic strain, giving μ_eff = q_c + a I^b.
* Dissipative stress σ^d = 2 a d̄^b ρ_s^{b/2} p_e^{1−b/2} γ̇^{b−1} d′ (seed Eq. 4, division-free
  form) with d̄ = φ_s d_s + (1 − φ_s) d_l of the material point.
* Gas state: no stress when I₁ ≤ 0 (H(I₁) of the seed's Eq. 5), deviatoric strain reset.

This module holds the plane-strain NumPy reference of the point update (``fei_update_np``, strains
and stresses as (xx, yy, xy, zz), tension positive) and the energy, stress and oedometric helpers;
the compiled law is the engine's ``fei_tensor`` (engine/kernels.py, full tensor form).
docs/model.md gives every decision with the switch for the alternative.
"""

from __future__ import annotations

import numpy as np

from .params import (
    DRIVER_A,
    DRIVER_B,
    DRIVER_P,
    M_A,
    M_C,
    M_DL,
    M_DRIVER,
    M_DS,
    M_F,
    M_GFLOOR,
    M_H,
    M_KAPPA,
    M_KAPPA_T,
    M_MU_A,
    M_MU_B,
    M_QPHI,
    M_RC,
    M_RHO_S,
    M_SDF,
    M_ZETA,
)

#: 1/3 (a multiplication instead of a division by 3 in the compiled kernels)
THIRD = 1.0 / 3.0


# ---------------------------------------------------------------------------------------------
# NumPy reference (vectorised over points) and closed-form helpers used by the tests


def jaumann_predictor_np(L, dt, eps):
    """The Jaumann predictor ε* = ε + Δt (d + W ε − ε W) in plane strain: returns d = sym L and the in-plane trial strain (n, 2, 2)."""
    d = 0.5 * (L + np.swapaxes(L, 1, 2))
    w = 0.5 * (L - np.swapaxes(L, 1, 2))
    E2 = np.zeros_like(L)
    E2[:, 0, 0], E2[:, 1, 1] = eps[:, 0], eps[:, 1]
    E2[:, 0, 1] = E2[:, 1, 0] = eps[:, 2]
    return d, E2 + dt * (d + w @ E2 - E2 @ w)


def fei_update_np(prm, L, dt, eps, J, phi):
    """NumPy reference of the Fei et al. (2016) point update (plane strain) for arrays of points.

    L (n, 2, 2), eps (n, 4), J (n,), phi (n,). Returns (eps_new, sig, p, gdot, I, S, c, nu).
    """
    L = np.asarray(L, dtype=np.float64)
    eps = np.array(eps, dtype=np.float64)
    A, C, rho_s = prm[M_A], prm[M_C], prm[M_RHO_S]
    rho = prm[M_F] * rho_s / J
    d, E2 = jaumann_predictor_np(L, dt, eps)
    E3 = np.zeros((len(J), 3, 3))
    E3[:, :2, :2] = E2
    E3[:, 2, 2] = eps[:, 3]
    D3 = np.zeros((len(J), 3, 3))
    D3[:, :2, :2] = d
    eye = np.eye(3)
    Dp = D3 - np.trace(D3, axis1=1, axis2=2)[:, None, None] / 3.0 * eye
    gdot = np.sqrt(2.0 * np.einsum("nij,nij->n", Dp, Dp))
    I1 = -np.log(J)
    E0 = E3 - np.trace(E3, axis1=1, axis2=2)[:, None, None] / 3.0 * eye
    I2 = 0.5 * np.einsum("nij,nij->n", E0, E0)
    gas = I1 <= 0
    I1p = np.where(gas, 1.0, I1)
    cap = prm[M_RC] * I1p / prm[M_QPHI]
    scale = np.where(I2 > cap**2, cap / np.sqrt(np.where(I2 > 0, I2, 1.0)), 1.0)
    E0 = E0 * scale[:, None, None]
    E0[gas] = 0.0
    I2 = np.where(gas, 0.0, np.minimum(I2, cap**2))
    Enew = E0 - (I1 / 3.0)[:, None, None] * eye
    sq = np.sqrt(I1p)
    pe = np.where(gas, 0.0, 2.5 * A * I1p**1.5 + 0.5 * C * I2 / sq)
    a = prm[M_MU_A] * prm[M_SDF]
    b = prm[M_MU_B]
    dbar = phi * prm[M_DS] + (1.0 - phi) * prm[M_DL]
    g = np.maximum(gdot, prm[M_GFLOOR]) if b != 1.0 else gdot
    eta = (
        a
        * dbar**b
        * rho_s ** (0.5 * b)
        * pe ** (1.0 - 0.5 * b)
        * np.where(b == 1.0, 1.0, g ** (b - 1.0))
    )
    c = np.where(gas, 0.0, np.sqrt((3.75 * A + 2.0 * C) * sq / rho))
    zeta = prm[M_ZETA] * rho * c * prm[M_H]
    trd = np.trace(D3, axis1=1, axis2=2)
    S3 = (
        -pe[:, None, None] * eye
        + (C * sq)[:, None, None] * E0
        + 2.0 * eta[:, None, None] * Dp
        + (zeta * trd)[:, None, None] * eye
    )
    S3[gas] = 0.0
    inertial = np.where(pe > 0, gdot * dbar / np.sqrt(np.where(pe > 0, pe, 1.0) / rho_s), 0.0)
    drv = int(prm[M_DRIVER])
    if drv == DRIVER_A:
        S = eta * gdot
    elif drv == DRIVER_B:
        S = prm[M_KAPPA_T] * rho * (gdot * dbar) ** 2
    elif drv == DRIVER_P:
        S = pe.copy()
    else:
        S = -2.0 * eta * Dp[:, 1, 1]
    S = np.where(gas, 0.0, S * prm[M_KAPPA])
    nu = np.where(gas, 0.0, (eta + zeta) / rho)
    eps_new = np.stack([Enew[:, 0, 0], Enew[:, 1, 1], Enew[:, 0, 1], Enew[:, 2, 2]], axis=1)
    sig = np.stack([S3[:, 0, 0], S3[:, 1, 1], S3[:, 0, 1], S3[:, 2, 2]], axis=1)
    return eps_new, sig, pe, gdot, np.where(gas, 0.0, inertial), S, c, nu


def elastic_energy(eps3: np.ndarray, A: float, C: float) -> float:
    """Jiang–Liu energy w_e = A I₁^{5/2} + C I₁^{1/2} I₂ of a 3×3 elastic strain (seed Eq. 2)."""
    I1 = -np.trace(eps3)
    E0 = eps3 + I1 / 3.0 * np.eye(3)
    I2 = 0.5 * np.sum(E0 * E0)
    return A * I1**2.5 + C * I1**0.5 * I2


def elastic_stress(eps3: np.ndarray, A: float, C: float) -> np.ndarray:
    """σ^e = −p_e 1 + C √I₁ ε⁰ of a 3×3 elastic strain (docs/model.md §1, step 5)."""
    I1 = -np.trace(eps3)
    E0 = eps3 + I1 / 3.0 * np.eye(3)
    I2 = 0.5 * np.sum(E0 * E0)
    pe = 2.5 * A * I1**1.5 + 0.5 * C * I2 / np.sqrt(I1)
    return -pe * np.eye(3) + C * np.sqrt(I1) * E0


def oedometric_strain(p_yy: np.ndarray, A: float, C: float) -> np.ndarray:
    """Compaction e ≥ 0 of ε^e = diag(0, −e, 0) carrying σ_yy = −p_yy (docs/model.md §3)."""
    return (np.maximum(p_yy, 0.0) / (2.5 * A + 5.0 * C / 6.0)) ** (2.0 / 3.0)
