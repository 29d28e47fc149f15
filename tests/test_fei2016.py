"""The Fei et al. (2016) model at the material-point level (docs/model.md §1, §3)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from segmpm.config import load_config
from segmpm.engine.codegen import for_material
from segmpm.engine.records import XX, XY, YY, ZZ, Points, material_record
from segmpm.materials import pack_material
from segmpm.materials.fei2016 import elastic_energy, elastic_stress
from segmpm.materials.params import M_A, M_C

A = 1.79e9
QPHI = 0.38
C = 5 * QPHI**2 * A


def fei_update(prm, l00, l01, l10, l11, dt, exx, eyy, exy, ezz, J, phi):
    """One point through the engine's 2-D material pass (``update_stress`` of the law of
    ``prm``): the new state in the plane-strain order of the NumPy reference, (ε_xx, ε_yy, ε_xy,
    ε_zz, σ_xx, σ_yy, σ_xy, σ_zz, p_e, γ̇, I, S, c, ν)."""
    mat = material_record(prm)
    k = for_material(2, mat)
    eps = np.zeros((4, 1))
    eps[[XX, YY, XY, ZZ], 0] = exx, eyy, exy, ezz
    P = Points(x=np.zeros((2, 1)), v=np.zeros((2, 1)), C=np.zeros((4, 1)), mass=np.ones(1),
               vol0=np.ones(1), J=np.array([float(J)]), eps=eps, sig=np.zeros((4, 1)),
               phi=np.array([float(phi)]), gf=np.zeros(1), diag=np.zeros((6, 1)),
               s_int=np.zeros(1), g_int=np.zeros(1),
               lg=np.array([[l00], [l01], [l10], [l11]], dtype=np.float64),
               flags=np.zeros(1, dtype=np.int8), cursor=np.zeros(1, dtype=np.int32),
               x_old=np.zeros((2, 0)))  # fmt: skip
    k.update_stress(P, mat, dt, True, 1)
    e, s, d = P.eps[[XX, YY, XY, ZZ], 0], P.sig[[XX, YY, XY, ZZ], 0], P.diag[:, 0]
    return (*e, *s, *d)


def test_stress_is_energy_derivative(rng):
    """σ^e = ∂w_e/∂ε^e (docs/model.md §1), by central finite differences, inside the convex
    region."""
    for _ in range(20):
        I1 = 10 ** rng.uniform(-6, -3)
        dev = rng.normal(size=(3, 3))
        dev = 0.5 * (dev + dev.T)
        dev -= np.trace(dev) / 3 * np.eye(3)
        dev *= rng.uniform(0.1, 0.9) * I1 / QPHI / math.sqrt(0.5 * np.sum(dev * dev))
        eps = dev - I1 / 3 * np.eye(3)
        sig = elastic_stress(eps, A, C)
        h = 1e-6 * I1
        fd = np.zeros((3, 3))
        for i in range(3):
            for j in range(3):
                e = np.zeros((3, 3))
                e[i, j] = h
                fd[i, j] = (elastic_energy(eps + e, A, C) - elastic_energy(eps - e, A, C)) / (2 * h)
        fd = 0.5 * (fd + fd.T)  # derivative w.r.t. a symmetric tensor
        np.testing.assert_allclose(sig, fd, rtol=1e-6, atol=1e-9 * np.abs(sig).max())


def test_convexity_limit_ratio_and_moduli():
    """√J₂/p_e = q_φ·2u/(1+u²): maximum q_φ at the convexity limit u = 1; K/G = 1.5/q_φ²."""
    I1 = 1e-5
    ratios = []
    for u in np.linspace(0.05, 2.0, 40):
        e = u * I1 / QPHI  # pure shear ε⁰_xy = ε⁰_yx = e has √I₂ = e
        eps = np.zeros((3, 3))
        eps[0, 1] = eps[1, 0] = e
        eps -= I1 / 3 * np.eye(3)
        dev = eps + I1 / 3 * np.eye(3)
        u_true = QPHI * math.sqrt(0.5 * np.sum(dev * dev)) / I1
        sig = elastic_stress(eps, A, C)
        p = -np.trace(sig) / 3
        s = sig + p * np.eye(3)
        r = math.sqrt(0.5 * np.sum(s * s)) / p
        assert abs(r - QPHI * 2 * u_true / (1 + u_true**2)) < 1e-12
        ratios.append((u_true, r))
    u_arr, r_arr = np.array(ratios).T
    assert abs(r_arr.max() - QPHI) < 1e-3 and abs(u_arr[np.argmax(r_arr)] - 1) < 0.06
    # moduli of the isotropic state: K = dp/dI₁ = 3.75 A √I₁, G = C √I₁ / 2
    K = 3.75 * A * math.sqrt(I1)
    h = 1e-9
    p = lambda i1: -np.trace(elastic_stress(-i1 / 3 * np.eye(3), A, C)) / 3  # noqa: E731
    assert abs((p(I1 + h) - p(I1 - h)) / (2 * h) / K - 1) < 1e-6
    eps = -I1 / 3 * np.eye(3)
    g = 1e-9
    eps[0, 1] = eps[1, 0] = g / 2
    G = elastic_stress(eps, A, C)[0, 1] / g
    assert abs(G / (C * math.sqrt(I1) / 2) - 1) < 1e-9
    assert abs(K / G - 1.5 / QPHI**2) < 1e-9


def _shear_history(rate: float, strain: float, I1: float, prm: np.ndarray):
    """Homogeneous simple shear v_x = γ̇ y at constant volume: τ/p along the strain history."""
    n = 4000
    dt = strain / rate / n
    eps = np.array([0.0, 0.0, 0.0, 0.0]) - I1 / 3 * np.array([1, 1, 0, 1])
    J = math.exp(-I1)
    out = []
    for k in range(n):
        r = fei_update(prm, 0.0, rate, 0.0, 0.0, dt, eps[0], eps[1], eps[2], eps[3], J, 0.5)
        eps = np.array(r[:4])
        out.append(((k + 1) * dt * rate, r[6], r[8], r[10]))  # strain, σ_xy, p_e, I
    return np.array(out)


def test_simple_shear_elastic_rise_cap_and_mu_of_I():
    cfg = load_config(preset="chute_seed", overrides=["material.stiffness_scale=1.0"])
    prm = pack_material(cfg)
    I1 = 2e-5
    G = prm[M_C] * math.sqrt(I1) / 2
    qc = QPHI * 2 * 0.95 / (1 + 0.95**2)
    # quasi-static: elastic rise with slope G, then saturation at q_c p
    h = _shear_history(1e-6, 20 * I1 / QPHI, I1, prm)
    g, tau, p = h[:, 0], h[:, 1], h[:, 2]
    early = g < 0.1 * I1 / QPHI
    np.testing.assert_allclose(tau[early] / g[early], G, rtol=2e-2)
    assert abs(tau[-1] / p[-1] / qc - 1) < 1e-4
    # the cap is reached after a strain of order I₁/q_φ
    reach = g[np.argmax(tau / p > 0.999 * qc)]
    assert 0.5 * I1 / QPHI < reach < 3 * I1 / QPHI
    # rate sweep: τ/p = q_c + a I (b = 1) within 2 %
    for rate in (1.0, 10.0, 50.0, 200.0, 1000.0):
        h = _shear_history(rate, 30 * I1 / QPHI, I1, prm)
        tau, p, inert = h[-1, 1], h[-1, 2], h[-1, 3]
        expect_I = rate * 2.5e-3 / math.sqrt(p / 2650.0)
        assert abs(inert / expect_I - 1) < 1e-9
        assert abs(tau / p / (qc + 0.46 * inert) - 1) < 0.02, (rate, tau / p, qc + 0.46 * inert)


def test_sigma_d_factor_and_mean_diameter():
    """σ^d scales with sigma_d_factor and with d̄ = φ d_s + (1 − φ) d_l."""
    base = pack_material(
        load_config(preset="chute_seed", overrides=["material.stiffness_scale=1e-3"])
    )
    half = pack_material(
        load_config(
            preset="chute_seed",
            overrides=["material.stiffness_scale=1e-3", "material.sigma_d_factor=0.5"],
        )
    )
    I1 = 1e-3
    args = (0.0, 50.0, 0.0, 0.0, 0.0, -I1 / 3, -I1 / 3, 0.0, -I1 / 3, math.exp(-I1))
    r_full = fei_update(base, *args, 0.5)
    r_half = fei_update(half, *args, 0.5)
    r_small = fei_update(base, *args, 1.0)
    assert abs(r_half[6] / r_full[6] - 0.5) < 1e-12  # only σ^d is present at zero elastic shear
    assert abs(r_small[6] / r_full[6] - 2.0 / 2.5) < 1e-12


def test_gas_state_is_stress_free():
    prm = pack_material(
        load_config(preset="chute_seed", overrides=["material.stiffness_scale=1e-3"])
    )
    r = fei_update(prm, 3.0, 5.0, -2.0, 1.0, 1e-4, 1e-4, -2e-4, 3e-5, 0.0, 1.01, 0.5)
    assert all(v == 0.0 for v in r[4:8]) and r[8] == 0.0 and r[11] == 0.0
    assert r[0] == r[1] == r[3] == pytest.approx(math.log(1.01) / 3) and r[2] == 0.0


def test_stiffness_scale_scales_A_and_C_together():
    p1 = pack_material(load_config(preset="chute_seed", overrides=["material.stiffness_scale=1.0"]))
    p2 = pack_material(
        load_config(preset="chute_seed", overrides=["material.stiffness_scale=1e-3"])
    )
    assert p2[M_A] / p1[M_A] == pytest.approx(1e-3) and p2[M_C] / p1[M_C] == pytest.approx(1e-3)
    assert p1[M_C] == pytest.approx(5 * QPHI**2 * A)
