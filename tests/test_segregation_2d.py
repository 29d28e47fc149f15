"""Fully 2-D transport: fluxes on x- and y-faces, blocks of points that do not fill the grid."""

from __future__ import annotations

import numpy as np

from segmpm.engine.codegen import kernels
from segmpm.segregation.closures import make_params
from segmpm.segregation.diagnostics import small_grain_volume
from segmpm.segregation.grid import allocate_work, concentration_step, make_conc_grid
from segmpm.segregation.reference import steady_logit_profile, strip_layout

RHO, ETA, C_D, B_KS = 1590.0, 1.11e-5, 6.8, 0.39


def test_2d_block_reaches_the_boltzmann_steady_state() -> None:
    """A block (4 × 3 mm) inside a larger closed grid, S(x, y) = a x + b y + c x y.

    With zero flux on every boundary the zero-flux state logit φ = −b^{k,s} S/(ρη) + const is the
    2-D steady state, and the Scharfetter–Gummel flux makes it exact on every face.
    """
    s = 0.25e-3
    px, py, vol0 = strip_layout(0.004, 0.003, s, x0=0.002, y0=0.0)
    cg = make_conc_grid(0.0, 0.008, 0.0, 0.006, s, 0)  # the block fills a quarter of it
    work = allocate_work(cg)
    prm = make_params("hill_tan_reduced", rho_bulk=RHO, eta=ETA, c_D=C_D, b_k_small=B_KS)

    def s_of(x, y):
        return 30.0 * (x - 0.002) + 20.0 * y + 4000.0 * (x - 0.002) * y

    phi = np.full(px.size, 0.4)
    total0 = small_grain_volume(vol0, phi)
    t_int = 0.5
    nsub = 0
    for _ in range(120):  # 60 s ≈ 6 diffusion times of the block
        s_int = s_of(px, py) * t_int
        g_int = np.zeros_like(phi)
        nsub += concentration_step(px, py, vol0, phi, s_int, g_int, t_int, cg, prm, work)
    k = kernels(2)  # the engine's scratch rows: the x-face rates a, b
    assert np.any(work[k.C_AX] != 0.0) and np.any(work[k.C_BX] != 0.0)  # x-faces carried flux
    exact = steady_logit_profile(-B_KS * s_of(px, py) / (RHO * ETA), vol0, 0.4)
    err = np.max(np.abs(phi - exact))
    print(f"2-D block steady state: max error {err:.2e} after {nsub} substeps")
    assert err < 1e-9
    assert np.ptp(exact) > 0.2
    assert abs(small_grain_volume(vol0, phi) / total0 - 1.0) < 1e-13


def test_2d_heap_with_sloping_driver_conserves_and_stays_bounded() -> None:
    """A jittered triangular heap (non-layered free surface), S sloping in x and y."""
    rng = np.random.default_rng(5)
    s = 0.25e-3
    px, py, vol0 = strip_layout(0.02, 0.01, s, jitter=0.8, seed=2)
    keep = py < 0.01 * (1.0 - np.abs(px - 0.01) / 0.01)  # triangle of base 20 mm, height 10 mm
    px, py, vol0 = px[keep], py[keep], vol0[keep]
    cg = make_conc_grid(0.0, 0.03, 0.0, 0.015, 0.25e-3, 0)
    work = allocate_work(cg)
    prm = make_params("hill_tan_full", b_c_small=-0.1, gravity_xy=(4.3, -8.82))
    phi = rng.uniform(0.0, 1.0, px.size)
    total0 = small_grain_volume(vol0, phi)
    xs0 = np.dot(vol0 * phi, px) / total0
    t_int = 0.01
    for k in range(100):
        # the heap deforms a little between subcycles (a shear along x)
        qx = px + 2e-5 * k * py / 0.01
        s_int = (50.0 * qx + 80.0 * (0.01 - py)) * t_int
        g_int = np.full_like(phi, 5.0 * t_int)
        concentration_step(qx, py, vol0, phi, s_int, g_int, t_int, cg, prm, work)
        assert phi.min() >= 0.0 and phi.max() <= 1.0
        assert abs(small_grain_volume(vol0, phi) / total0 - 1.0) < 1e-12
    # predicted x-velocity (closures.py, hill_tan_full):
    # w_x = ((b^{c,s} − b^{k,s})/(c_D ρ)) ∂S/∂x − (b^{c,s}/c_D) g_x = −0.0023 + 0.063 m/s > 0:
    # the downslope gravity term with b^{c,s} < 0 wins over the S-gradient here
    w_x = (-0.1 - 0.39) / (6.8 * 1590.0) * 50.0 + 0.1 / 6.8 * 4.3
    xs1 = np.dot(vol0 * phi, px) / small_grain_volume(vol0, phi)
    print(f"heap: small-grain centroid moved {1e3 * (xs1 - xs0):.3f} mm in x (w_x = {w_x:.3f} m/s)")
    assert w_x > 0.0 and xs1 > xs0 + 1e-4


def test_periodic_x_transport_wraps_and_conserves() -> None:
    """S varying along x only, periodic strip: small grains collect at the minimum of S."""
    length = 0.006
    px, py, vol0 = strip_layout(length, 0.002, 0.25e-3)
    cg = make_conc_grid(0.0, length, 0.0, 0.002, 0.25e-3, 1)
    work = allocate_work(cg)
    prm = make_params("hill_tan_reduced")
    phi = np.full(px.size, 0.5)
    total0 = small_grain_volume(vol0, phi)
    x_min = 0.1e-3  # the minimum of S sits right at the periodic seam

    def s_of(x):
        return 0.1 * (1.0 - np.cos(2 * np.pi * (x - x_min) / length))

    for _ in range(200):
        s_int = s_of(px) * 0.05
        concentration_step(px, py, vol0, phi, s_int, np.zeros_like(phi), 0.05, cg, prm, work)
    exact = steady_logit_profile(-B_KS * s_of(px) / (RHO * ETA), vol0, 0.5)
    err = np.max(np.abs(phi - exact))
    print(f"periodic x steady state: max error {err:.2e}")
    assert err < 1e-3
    near_seam = np.abs(((px - x_min + length / 2) % length) - length / 2) < 0.5e-3
    assert phi[near_seam].mean() > 0.6
    assert abs(small_grain_volume(vol0, phi) / total0 - 1.0) < 1e-13
