"""Nonlocal granular fluidity (NGF) on the Jiang–Liu elasticity (``material.rheology =
"nonlocal"``; docs/model.md, "Nonlocal rheology").

Plastic flow follows the fluidity flow rule of Kamrin & Koval (2012) and Henann & Kamrin (2013):
the equivalent plastic shear rate is γ̇ᵖ = g μ, with μ = τ̄/p the stress ratio
(τ̄ = √(½ s:s)) and g the granular fluidity, a field that obeys the dynamic equation of Kamrin &
Henann (2015)

    t₀ ∂g/∂t = A² d̄² ∇²g − (μ_s − μ) g − b μ √(ρ_s d̄²/p) g².

Its homogeneous steady state is g_loc = √(p/ρ_s d̄²) (μ − μ_s)/(b μ) (μ > μ_s, else 0): locally
μ = μ_s + b I, the linear μ(I) of the local model with μ_s for q_c and b for a. The g² term's
√(ρ_s d̄²/p), singular at a free surface, uses p̃ = max(p, p_min), p_min the weight of
``material.fluidity_floor_layers`` grain layers (docs/model.md).

Per material point and step (the engine's ``ngf_tensor``; its plane-strain NumPy reference
``ngf_update_np``): the objective elastic predictor of the Fei model,
the Jiang–Liu convexity guard √I₂ ≤ r_c I₁/q_φ on the trial state, then the implicit
(unconditionally stable) return of the deviatoric elastic strain,
ε⁰ ← ε⁰_tr p/(p + G Δt g) (that is τ = τ_tr p/(p + G Δt g), G = C√I₁/2 the shear modulus, p the
Jiang–Liu pressure of the returned state: ``return_factor``), then the stress. There is no σ^d: the rate dependence is
the fluidity's. The fluidity itself is advanced between steps by the engine's ``fluidity_step``:
nonlocal diffusion on the MPM grid, then ``relax_logistic`` at the points (the exact solution of the local
part for coefficients frozen over the interval). g = 0 where the material is disconnected
(gas, p ≤ 0).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .fei2016 import jaumann_predictor_np
from .params import (
    DRIVER_A,
    DRIVER_B,
    DRIVER_C,
    DRIVER_P,
    M_A,
    M_C,
    M_DL,
    M_DRIVER,
    M_DS,
    M_F,
    M_H,
    M_KAPPA,
    M_KAPPA_G,
    M_KAPPA_T,
    M_MU_S,
    M_NGF_B,
    M_PFLOOR,
    M_QPHI,
    M_RC,
    M_RHO_S,
    M_T0,
    M_ZETA,
)

#: the fluidity a point with μ > μ_s and g = 0 exactly starts from, as a fraction of its g_loc:
#: g = 0 is an (unstable) fixed point of the local equation, so material that has never flowed
#: (or has just re-contacted from a gas) would otherwise never flow. Only g = 0 is seeded: a
#: decaying fluidity (a layer below h_stop) is never re-injected
SEED_FRACTION = 1.0e-3


#: Newton iterations of ``return_factor`` (from the explicit estimate; 6 reach round-off for
#: a2 ≤ 2 (a0 + k) and G Δt g/p up to 10³, tests/test_nonlocal.py)
RETURN_ITERATIONS = 6


@njit(cache=True, error_model="numpy", inline="always")
def return_factor(a0, a2, k):
    """The factor f ∈ (0, 1] of the implicit return ε⁰ = f ε⁰_tr of the flow rule γ̇ᵖ = g μ:
    f (p(f) + G Δt g) = p(f), with the Jiang–Liu pressure of the returned state
    p(f) = a0 + a2 f² (a0 = 2.5 A I₁^{3/2}, a2 = ½ C I₂,tr/√I₁, k = G Δt g). It is τ = τ_tr
    p/(p + G Δt g) with p the pressure of the returned state, so that a steady shear gives
    γ̇ = g τ/p exactly. The cubic a2 f²(f − 1) + (a0 + k) f − a0 = 0 has one root in (0, 1]
    (it increases there when a2 < 3 (a0 + k): its slope a2 f(3f − 2) + a0 + k ≥ a0 + k − a2/3;
    the caller keeps a2 ≤ 2 (a0 + k)); Newton from f = a0/(a0 + k), a fixed number of
    iterations, so the loop stays branch-free."""
    f = a0 / (a0 + k)  # a lower bound of the root (the cubic is ≤ 0 there)
    for _ in range(RETURN_ITERATIONS):
        r = a2 * f * f * (f - 1.0) + (a0 + k) * f - a0
        d = a2 * f * (3.0 * f - 2.0) + a0 + k
        f -= r / d
    return f


@njit(cache=True, error_model="numpy", inline="always")
def relax_local(g, mu, p, dbar, dt, prm):
    """The local part t₀ dg/dt = (μ − μ_s) g − b μ √(ρ_s d̄²/p̃) g² over ``dt`` (p̃ = max(p, p_min),
    ``M_PFLOOR``), exactly for μ and p frozen (:func:`relax_logistic` with the coefficients of
    the packed record ``prm``)."""
    return relax_logistic(g, mu, p, dbar, dt, prm[M_RHO_S], prm[M_MU_S], prm[M_T0],
                          prm[M_NGF_B], prm[M_PFLOOR])  # fmt: skip


@njit(cache=True, error_model="numpy", inline="always")
def relax_logistic(g, mu, p, dbar, dt, rho_s, mu_s, t0, b, p_floor):
    """The local part t₀ dg/dt = (μ − μ_s) g − b μ √(ρ_s d̄²/p̃) g² over ``dt`` (p̃ = max(p, p_min)),
    exactly for μ and
    p frozen (a logistic equation: g → g_loc for μ > μ_s, g → 0 otherwise, monotonically and
    without a step limit). Disconnected material (p ≤ 0) has g = 0. A point with μ > μ_s and
    g = 0 starts from ``SEED_FRACTION`` g_loc. Scalar coefficients: the engine's fluidity update
    calls it, and :func:`relax_local` (which the tests check against an ODE solve) wraps it."""
    if not (p > 0.0):
        return 0.0
    if g != g:
        return g  # NaN propagates to the engine's check
    k = b * mu * dbar * math.sqrt(rho_s / max(p, p_floor)) / t0
    lam = (mu - mu_s) / t0
    if g < 0.0:
        g = 0.0
    if lam > 0.0:
        gl = lam / k
        if g == 0.0:
            g = SEED_FRACTION * gl
        # g(t) = 1 / (e^{−λt}/g + k (1 − e^{−λt})/λ): no overflow for λ t ≫ 1
        em = math.exp(-lam * dt)
        return 1.0 / (em / g + (1.0 - em) / gl)
    if g == 0.0:
        return 0.0
    x = lam * dt
    if x < -1e-8:
        e = math.exp(x)
        return g * e / (1.0 + k * g * math.expm1(x) / lam)
    return g / (1.0 + k * g * dt)


# ---------------------------------------------------------------------------------------------
# NumPy reference


def ngf_update_np(prm, L, dt, eps, J, phi, gf):
    """NumPy reference of the nonlocal point update (plane strain) for arrays of points (I₁ = −ln J).

    L (n, 2, 2), eps (n, 4), J, phi, gf (n,). Returns (eps_new, sig, p, gdot, I, S, c, nu).
    """
    L = np.asarray(L, dtype=np.float64)
    eps = np.array(eps, dtype=np.float64)
    gf = np.asarray(gf, dtype=np.float64)
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
    gas = I1 <= 0
    I1p = np.where(gas, 1.0, I1)
    sq = np.sqrt(I1p)
    E0 = E3 - np.trace(E3, axis1=1, axis2=2)[:, None, None] / 3.0 * eye
    I2 = 0.5 * np.einsum("nij,nij->n", E0, E0)
    a0 = 2.5 * A * I1p**1.5
    k = 0.5 * C * sq * dt * gf
    lim = 4.0 * (a0 + k) * sq / C  # a2 = ½ C I₂/√I₁ ≤ 2 (a0 + k): a unique root
    pull = np.where(I2 > lim, np.sqrt(lim / np.where(I2 > 0, I2, 1.0)), 1.0)
    I2 = np.minimum(I2, lim)
    factor = return_factor_np(a0, 0.5 * C * I2 / sq, k)
    I2 = I2 * factor**2
    cap = prm[M_RC] * I1p / prm[M_QPHI]  # the convexity guard on the returned state
    factor = factor * pull * np.where(I2 > cap**2, cap / np.sqrt(np.where(I2 > 0, I2, 1.0)), 1.0)
    I2 = np.minimum(I2, cap**2)
    E0 = E0 * factor[:, None, None]
    E0[gas] = 0.0
    I2 = np.where(gas, 0.0, I2)
    Enew = E0 - (I1 / 3.0)[:, None, None] * eye
    pe = np.where(gas, 0.0, 2.5 * A * I1p**1.5 + 0.5 * C * I2 / sq)
    dbar = phi * prm[M_DS] + (1.0 - phi) * prm[M_DL]
    c = np.where(gas, 0.0, np.sqrt((3.75 * A + 2.0 * C) * sq / rho))
    zeta = prm[M_ZETA] * rho * c * prm[M_H]
    trd = np.trace(D3, axis1=1, axis2=2)
    S3 = -pe[:, None, None] * eye + (C * sq)[:, None, None] * E0 + (zeta * trd)[:, None, None] * eye
    S3[gas] = 0.0
    inertial = np.where(pe > 0, gdot * dbar / np.sqrt(np.where(pe > 0, pe, 1.0) / rho_s), 0.0)
    drv = int(prm[M_DRIVER])
    if drv == DRIVER_A:
        S = prm[M_NGF_B] * inertial * pe
    elif drv == DRIVER_B:
        S = prm[M_KAPPA_T] * rho * (gdot * dbar) ** 2
    elif drv == DRIVER_C:
        S = np.zeros_like(pe)
    elif drv == DRIVER_P:
        S = pe.copy()
    else:
        S = prm[M_KAPPA_G] * rho * (gf * dbar) ** 2
    S = np.where(gas, 0.0, S * prm[M_KAPPA])
    nu = np.where(gas, 0.0, zeta / rho)
    eps_new = np.stack([Enew[:, 0, 0], Enew[:, 1, 1], Enew[:, 0, 1], Enew[:, 2, 2]], axis=1)
    sig = np.stack([S3[:, 0, 0], S3[:, 1, 1], S3[:, 0, 1], S3[:, 2, 2]], axis=1)
    return eps_new, sig, pe, gdot, np.where(gas, 0.0, inertial), S, c, nu


def return_factor_np(a0, a2, k):
    """NumPy :func:`return_factor`: the root in (0, 1] of a2 f²(f − 1) + (a0 + k) f − a0 by
    bisection to round-off (independent of the Newton iteration of the compiled kernel)."""
    a0, a2, k = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in (a0, a2, k)))
    lo = np.zeros(a0.shape)
    hi = np.ones(a0.shape)
    for _ in range(64):
        mid = 0.5 * (lo + hi)
        r = a2 * mid * mid * (mid - 1.0) + (a0 + k) * mid - a0
        neg = r < 0
        lo = np.where(neg, mid, lo)
        hi = np.where(neg, hi, mid)
    return 0.5 * (lo + hi)


def stress_ratio_np(sig: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The stress ratio μ = √(½ s:s)/p (0 where p ≤ 0): sig (4, n) as (xx, yy, xy, zz), p (n,)."""
    sxx, syy, sxy, szz = sig
    m = (sxx + syy + szz) / 3.0
    tau = np.sqrt(0.5 * ((sxx - m) ** 2 + (syy - m) ** 2 + (szz - m) ** 2) + sxy**2)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(p > 0, tau / np.where(p > 0, p, 1.0), 0.0)


def local_fluidity_np(mu, p, dbar, rho_s, mu_s, b, p_min=0.0):
    """g_loc = √(p̃/(ρ_s d̄²)) (μ − μ_s)/(b μ), p̃ = max(p, p_min), for μ > μ_s and p > 0, else 0
    (1/s)."""
    mu, p, dbar = np.broadcast_arrays(*(np.asarray(a, dtype=np.float64) for a in (mu, p, dbar)))
    ok = (p > 0) & (mu > mu_s)
    with np.errstate(invalid="ignore", divide="ignore"):
        g = (
            np.sqrt(np.maximum(np.where(ok, p, 0.0), p_min) / rho_s)
            / dbar
            * (mu - mu_s)
            / (b * np.where(ok, mu, 1))
        )
    return np.where(ok, g, 0.0)


def relax_local_np(g, mu, p, dbar, dt, prm):
    """NumPy reference of :func:`relax_local`: the same logistic solution, element-wise."""
    g = np.array(g, dtype=np.float64)
    mu, p, dbar = (np.broadcast_to(np.asarray(a, dtype=np.float64), g.shape) for a in (mu, p, dbar))
    out = np.zeros_like(g)
    t0 = prm[M_T0]
    for i in np.ndindex(g.shape):
        if not p[i] > 0:
            continue
        k = prm[M_NGF_B] * mu[i] * dbar[i] * np.sqrt(prm[M_RHO_S] / max(p[i], prm[M_PFLOOR])) / t0
        lam = (mu[i] - prm[M_MU_S]) / t0
        gi = max(g[i], 0.0)
        if lam > 0:
            gl = lam / k
            gi = SEED_FRACTION * gl if gi == 0.0 else gi
            em = np.exp(-lam * dt)
            out[i] = 1.0 / (em / gi + (1.0 - em) / gl)
        elif gi == 0.0:
            out[i] = 0.0
        elif lam * dt < -1e-8:
            out[i] = gi * np.exp(lam * dt) / (1.0 + k * gi * np.expm1(lam * dt) / lam)
        else:
            out[i] = gi / (1.0 + k * gi * dt)
    return out
