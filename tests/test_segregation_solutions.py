"""Concentration kernel against the reference solutions of docs/segregation.md §4.

Shocks (Gray & Thornton 2005), zero-flux steady states, a transient with constant w and D
against an independent fine-grid solution, and the sign / mirror rules (docs/segregation.md §1).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.sparse import diags

from segmpm.segregation.closures import make_params
from segmpm.segregation.diagnostics import segregation_index, species_centroids
from segmpm.segregation.grid import allocate_work, concentration_step, make_conc_grid
from segmpm.segregation.reference import shock_positions, steady_logit_profile, strip_layout

RHO = 1590.0  # bulk density f ρ_s, kg/m³
G = 9.81
SLOPE = np.deg2rad(26.0)
ETA, C_D, B_KS = 1.11e-5, 6.8, 0.39


def _column(length, depth, spacing, hc, periodic=1, top_pad=0.0, jitter=0.0):
    px, py, vol0 = strip_layout(length, depth, spacing, jitter=jitter, seed=3)
    cg = make_conc_grid(0.0, length, 0.0, depth + top_pad, hc, periodic)
    return px, py, vol0, cg, allocate_work(cg)


def _run(px, py, vol0, phi, cg, work, prm, t_end, t_int, s_of_y=None, gdot=0.0):
    """Drive concentration_step with S(y) and γ̇ prescribed (time integrals over each subcycle)."""
    n = int(round(t_end / t_int))
    nsub = 0
    s_int = np.zeros_like(phi)
    g_int = np.zeros_like(phi)
    for _ in range(n):
        if s_of_y is not None:
            s_int[:] = s_of_y(py) * t_int
        g_int[:] = gdot * t_int
        nsub += concentration_step(px, py, vol0, phi, s_int, g_int, t_int, cg, prm, work)
    return nsub


def _layer_means(py, phi):
    ys = np.unique(np.round(py, 12))
    return ys, np.array([phi[np.isclose(py, y, atol=1e-12)].mean() for y in ys])


def _crossing(y, f, level):
    """First y where the (monotone near the level) profile f crosses ``level`` (linear interp.)."""
    s = np.sign(f - level)
    k = np.nonzero(s[:-1] != s[1:])[0][0]
    return y[k] + (level - f[k]) * (y[k + 1] - y[k]) / (f[k + 1] - f[k])


@pytest.mark.parametrize("hc", [0.25e-3, 0.5e-3])
def test_gray_thornton_inviscid_shocks(hc: float) -> None:
    """D = 0, constant q, uniform φ₀: shocks at y = qφ₀t and H − q(1−φ₀)t within 2 % of H."""
    depth, q, phi0 = 0.02, 0.01, 0.5
    px, py, vol0, cg, work = _column(0.012, depth, 0.25e-3, hc)  # 4 MPs per 0.5 mm cell
    prm = make_params("gray_thornton", q=q, diffusivity=0.0)
    phi = np.full(px.size, phi0)
    total0 = np.dot(vol0, phi)
    t_done = 0.0
    for t_end in (0.3 * depth / q, 0.6 * depth / q):
        _run(px, py, vol0, phi, cg, work, prm, t_end - t_done, 1e-3)
        t_done = t_end
        y, f = _layer_means(py, phi)
        y_small_top = _crossing(y, f, 0.5 * (1.0 + phi0))  # middle of the jump 1 → φ₀
        y_large_bot = _crossing(y[::-1], f[::-1], 0.5 * phi0)  # middle of the jump φ₀ → 0
        exp_s, exp_l = shock_positions(q, phi0, depth, t_end)
        err = max(abs(y_small_top - exp_s), abs(y_large_bot - exp_l)) / depth
        print(f"hc={hc:.2e} t={t_end:.2f}s shock error {100 * err:.2f}% of H")
        assert err <= 0.02
    assert abs(np.dot(vol0, phi) / total0 - 1.0) < 1e-13


def _sidewall_driver(depth, kappa):
    """κ S_A(ζ) = κ ρ g cosθ ζ (α − βζ), ζ = H − y (docs/segregation.md §1), zero below ζ_f."""
    alpha, beta = np.tan(SLOPE) - 0.38, 0.3 / 0.022

    def s_of_y(y):
        zeta = np.clip(depth - y, 0.0, None)
        return kappa * RHO * G * np.cos(SLOPE) * zeta * np.clip(alpha - beta * zeta, 0.0, None)

    return s_of_y


@pytest.mark.parametrize("driver", ["sidewall", "linear"])
@pytest.mark.parametrize(
    ("hc", "jitter"),
    [(0.25e-3, 0.0), (0.25e-3, 0.9), (0.5e-3, 0.0)],
    ids=["aligned", "jittered", "coarse"],
)
def test_steady_state_matches_closed_form(driver: str, hc: float, jitter: float) -> None:
    """Long-time profile against the closed form φ/(1−φ) = K exp(−b^{k,s} S/(ρη)); RMS ≤ 0.01.

    Points at the cell centres (aligned) reproduce it to round-off: the Scharfetter–Gummel
    zero-flux state is exact at any h_c. Jittered points and 2 × 2 points per cell (coarse)
    carry the sub-cell interpolation error of the tent mapping, O(h_c² φ'').
    """
    depth = 0.008
    if driver == "sidewall":
        s_of_y = _sidewall_driver(depth, kappa=0.05)  # b S/(ρη) spans ≈ 3.3: partial segregation
    else:
        s_of_y = lambda y: 20.0 * y  # noqa: E731  (S grows upward: 0.16 Pa over the layer)
    px, py, vol0, cg, work = _column(0.003, depth, 0.25e-3, hc, jitter=jitter)
    prm = make_params("hill_tan_reduced", rho_bulk=RHO, eta=ETA, c_D=C_D, b_k_small=B_KS)
    phi = np.full(px.size, 0.5)
    t_end = 6.0 * depth**2 / (ETA / C_D)  # six diffusion times
    nsub = _run(px, py, vol0, phi, cg, work, prm, t_end, 0.25, s_of_y)
    exact = steady_logit_profile(-B_KS * s_of_y(py) / (RHO * ETA), vol0, 0.5)
    rms = float(np.sqrt(np.mean((phi - exact) ** 2)))
    print(f"steady {driver} hc={hc:.2e} jitter={jitter}: RMS {rms:.2e} after {nsub} substeps")
    assert rms <= (1e-10 if (hc == 0.25e-3 and jitter == 0.0) else 0.01)
    assert np.ptp(exact) > 0.4  # the profile is far from uniform


def _fine_reference(depth, q, d, t_end, phi0, n=1280):
    """Independent solution: 2nd-order central FV method of lines, implicit Radau (scipy)."""
    h = depth / n

    def rhs(_t, f):
        fm = 0.5 * (f[1:] + f[:-1])
        flux = -q * fm * (1.0 - fm) - d * (f[1:] - f[:-1]) / h
        flux = np.concatenate([[0.0], flux, [0.0]])
        return -(flux[1:] - flux[:-1]) / h

    sparsity = diags([1.0, 1.0, 1.0], [-1, 0, 1], shape=(n, n))
    sol = solve_ivp(
        rhs,
        (0.0, t_end),
        np.full(n, phi0),
        method="Radau",
        rtol=1e-10,
        atol=1e-12,
        jac_sparsity=sparsity,
    )
    assert sol.success
    return (np.arange(n) + 0.5) * h, sol.y[:, -1]


def test_transient_convergence_order() -> None:
    """Constant w = −q and D (Gray–Thornton with diffusion): error falls at ≥ 0.8 × order 2.

    Scharfetter–Gummel is second order in space for a fixed Péclet number; forward Euler with the
    diffusive step Δt ∝ h_c² is second order in h_c as well, so the theoretical order is 2.
    """
    depth, q, d, t_end, phi0 = 0.01, 0.002, 2e-6, 1.0, 0.5
    y_ref, f_ref = _fine_reference(depth, q, d, t_end, phi0)
    prm = make_params("gray_thornton", q=q, diffusivity=d)
    errors = []
    sizes = (20, 40, 80, 160)
    for n in sizes:
        h = depth / n
        px, py, vol0, cg, work = _column(2 * h, depth, h, h)  # one MP per cell, at the centre
        phi = np.full(px.size, phi0)
        _run(px, py, vol0, phi, cg, work, prm, t_end, t_end / 100)
        errors.append(np.mean(np.abs(phi - np.interp(py, y_ref, f_ref))))
    errors = np.array(errors)
    orders = np.log2(errors[:-1] / errors[1:])
    print(f"transient L1 errors {errors} observed orders {orders}")
    assert np.all(orders >= 0.8 * 2.0)


def test_sign_small_grains_sink_when_s_grows_upward() -> None:
    """∂S/∂y > 0 with b^{k,s} > 0: small grains sink (the sign rule, docs/segregation.md §1)."""
    depth = 0.008
    px, py, vol0, cg, work = _column(0.002, depth, 0.25e-3, 0.25e-3)
    phi = np.full(px.size, 0.5)
    prm = make_params("hill_tan_reduced")
    _run(px, py, vol0, phi, cg, work, prm, 5.0, 0.05, lambda y: 40.0 * y)
    y_s, y_l = species_centroids(py, vol0, phi)
    assert y_s < y_l
    assert segregation_index(py, vol0, phi) > 0.1
    # the reverse gradient makes them rise
    phi2 = np.full(px.size, 0.5)
    _run(px, py, vol0, phi2, cg, work, prm, 5.0, 0.05, lambda y: 40.0 * (depth - y))
    assert segregation_index(py, vol0, phi2) < -0.1


@pytest.mark.parametrize("flux", ["sg", "upwind"])
def test_flipping_bks_mirrors_profile(flux: str) -> None:
    """b^{k,s} → −b^{k,s} maps φ → 1 − φ exactly for φ₀ = 0.5 (docs/segregation.md §4)."""
    depth = 0.008
    px, py, vol0, cg, work = _column(0.003, depth, 0.25e-3, 0.5e-3)
    s_of_y = _sidewall_driver(depth, kappa=0.3)
    out = []
    for b in (B_KS, -B_KS):
        phi = np.full(px.size, 0.5)
        prm = make_params("hill_tan_reduced", flux=flux, b_k_small=b)
        _run(px, py, vol0, phi, cg, work, prm, 2.0, 0.02, s_of_y)
        out.append(phi)
    assert np.max(np.abs(out[0] - (1.0 - out[1]))) < 1e-12
    assert np.ptp(out[0]) > 0.3


def test_constant_s_gives_pure_diffusion() -> None:
    """S ≡ const: no segregation velocity, an initially uniform mixture stays uniform."""
    px, py, vol0, cg, work = _column(0.002, 0.004, 0.25e-3, 0.25e-3)
    phi = np.full(px.size, 0.3)
    nsub = _run(px, py, vol0, phi, cg, work, make_params(), 1.0, 0.1, lambda y: 0 * y + 2.0)
    assert nsub > 0
    assert np.max(np.abs(phi - 0.3)) < 1e-14


def test_closures_give_expected_direction() -> None:
    """Every closure with its segregation term on sends small grains down in a sheared layer."""
    depth = 0.006
    px, py, vol0, cg, work = _column(0.002, depth, 0.25e-3, 0.25e-3)
    cases = {
        "gray_thornton": make_params("gray_thornton", q=0.01, diffusivity=1e-7),
        "gray_thornton_shear": make_params(
            "gray_thornton", q=0.2, q_shear_scaled=True, diffusivity=1e-7
        ),
        "fan2014": make_params("fan2014", fan_S=1e-4, fan_D_coeff=0.042),
        # Eq. 1 with S ≡ const: only the gravity term with b^{c,s} < 0 acts, small grains sink
        "hill_tan_full": make_params(
            "hill_tan_full", b_c_small=-0.05, gravity_xy=(G * np.sin(SLOPE), -G * np.cos(SLOPE))
        ),
    }
    for name, prm in cases.items():
        phi = np.full(px.size, 0.5)
        _run(px, py, vol0, phi, cg, work, prm, 0.3, 0.01, lambda y: 0 * y + 1.0, gdot=20.0)
        si = segregation_index(py, vol0, phi)
        print(f"{name}: SI = {si:.3f}")
        assert si > 0.05, name


def test_sidewall_chute_surface_layer_thickness() -> None:
    """Seed chute, proxy A at κ = 1 (docs/segregation.md §1): a φ > 0.9 layer forms at the free
    surface, 1.35 mm thick after 0.1 s and 1.85 mm after 0.5 s (an independent 1-D computation
    made outside this code)."""
    depth, s = 0.0375, 0.25e-3
    px, py, vol0, cg, work = _column(0.012, depth, s, s, top_pad=0.3 * depth)
    phi = np.full(px.size, 0.5)
    prm = make_params("hill_tan_reduced", rho_bulk=RHO, eta=ETA, c_D=C_D, b_k_small=B_KS)
    s_of_y = _sidewall_driver(depth, kappa=1.0)
    t_done = 0.0
    for t_end, expected in ((0.1, 1.35e-3), (0.5, 1.85e-3)):
        _run(px, py, vol0, phi, cg, work, prm, t_end - t_done, 1e-3, s_of_y)
        t_done = t_end
        y, f = _layer_means(py, phi)
        thickness = depth - (y[f <= 0.9].max() + 0.5 * s)
        print(f"surface layer φ > 0.9 at t = {t_end} s: {1e3 * thickness:.2f} mm")
        assert abs(thickness - expected) <= s  # within one cell
