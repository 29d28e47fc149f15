"""Concentration kernel (the engine's 2-D step, through segregation.grid.concentration_step):
agreement with the NumPy twin, conservation, boundedness, set-up.

docs/segregation.md §2 (k): Σ_p V⁰_p φ_p is conserved to round-off and 0 ≤ φ_p ≤ 1 always.
"""

from __future__ import annotations

import zlib

import numpy as np
import pytest

from segmpm.segregation.closures import (
    MODEL_CODES,
    N_PARAMS,
    P_DT_TARGET,
    P_GX,
    P_GY,
    P_HC,
    P_MODEL,
    P_RHO_BULK,
    make_params,
    pack_params,
)
from segmpm.segregation.grid import (
    ConcGrid,
    allocate_work,
    concentration_step,
    make_conc_grid,
    tent_weights,
)
from segmpm.segregation.reference import concentration_step_ref, strip_layout

RHO = 1590.0
G = 9.81
SLOPE = np.deg2rad(26.0)


def _random_case(rng: np.random.Generator, periodic: int, n: int = 500):
    lx, ly = 0.004, 0.005
    px = rng.uniform(0.0, lx, n)
    py = rng.uniform(0.0, ly, n)
    vol0 = rng.uniform(0.5, 1.5, n) * (0.25e-3) ** 2
    phi = rng.uniform(0.0, 1.0, n)
    phi[: n // 20] = 0.0
    phi[n // 20 : n // 10] = 1.0
    cg = make_conc_grid(0.0, lx, 0.0, ly, 0.25e-3, periodic)
    return px, py, vol0, phi, cg


@pytest.mark.parametrize(
    "model", ["hill_tan_reduced", "hill_tan_full", "gray_thornton", "fan2014", "liu_henann"]
)
@pytest.mark.parametrize("flux", ["sg", "upwind"])
@pytest.mark.parametrize("periodic", [1, 0])
def test_kernel_agrees_with_numpy_reference(model: str, flux: str, periodic: int) -> None:
    """The engine's compiled step and the NumPy twin (segregation.reference) agree to ~1e-12 on
    random layouts and random S fields."""
    # a seed that is the same in every process (hash() of a str is randomised per process)
    rng = np.random.default_rng(zlib.crc32(f"{model}-{flux}-{periodic}".encode()))
    px, py, vol0, phi, cg = _random_case(rng, periodic)
    work = allocate_work(cg)
    prm = make_params(
        model,
        flux=flux,
        b_c_small=-0.2,
        gravity_xy=(G * np.sin(SLOPE), -G * np.cos(SLOPE)),
        q_shear_scaled=model == "gray_thornton" and periodic == 1,
    )
    a = phi.copy()
    b = phi.copy()
    t_int = 2e-3
    for _ in range(5):
        s = rng.uniform(0.0, 0.5, a.size) * t_int  # S up to 0.5 Pa, random in space
        g = rng.uniform(0.0, 20.0, a.size) * t_int  # γ̇ up to 20 1/s
        sa, ga, sb, gb = s.copy(), g.copy(), s.copy(), g.copy()
        na = concentration_step(px, py, vol0, a, sa, ga, t_int, cg, prm, work)
        nb = concentration_step_ref(px, py, vol0, b, sb, gb, t_int, cg, prm)
        assert na == nb and na >= 1
        assert not sa.any() and not ga.any() and not sb.any() and not gb.any()
    assert np.max(np.abs(a - b)) < 1e-12
    assert np.max(np.abs(a - phi)) > 1e-3  # something did happen


def test_conservation_and_bounds_over_1e4_substeps() -> None:
    """Σ V⁰ φ conserved to ≤ 1e-12 (relative) over ≥ 10⁴ substeps with moving points."""
    rng = np.random.default_rng(7)
    length, depth, s = 0.012, 0.008, 0.25e-3  # 4 MPs per 0.5 mm MPM cell
    px0, py0, vol0 = strip_layout(length, depth, s)
    cg = make_conc_grid(0.0, length, 0.0, depth + 2 * s, 0.25e-3, 1)
    work = allocate_work(cg)
    prm = make_params("hill_tan_reduced")
    phi = np.full(px0.size, 0.5)
    total0 = np.dot(vol0, phi)
    # sidewall-chute driver S_A(ζ) = ρ g cosθ ζ (α − βζ) (docs/segregation.md §1), κ = 1
    alpha, beta = np.tan(SLOPE) - 0.38, 0.3 / 0.022
    t_int = 0.05
    nsub = 0
    worst = 0.0
    while nsub < 10_000:
        # the points move (random jitter and shear along x) between subcycles
        px = px0 + rng.uniform(-0.4, 0.4, px0.size) * s + rng.uniform(0, 1) * length * py0 / depth
        py = py0 + rng.uniform(-0.4, 0.4, py0.size) * s
        zeta = np.clip(depth - py, 0.0, None)
        sa = RHO * G * np.cos(SLOPE) * zeta * np.clip(alpha - beta * zeta, 0.0, None)
        s_int = sa * t_int
        g_int = np.full_like(phi, 10.0 * t_int)
        nsub += concentration_step(px, py, vol0, phi, s_int, g_int, t_int, cg, prm, work)
        assert phi.min() >= 0.0 and phi.max() <= 1.0
        worst = max(worst, abs(np.dot(vol0, phi) / total0 - 1.0))
    print(f"conservation over {nsub} substeps: max relative drift {worst:.2e}")
    assert worst <= 1e-12
    assert phi.max() > 0.95 and phi.min() < 0.3  # strongly segregated: the test is not idle


@pytest.mark.parametrize(
    "model", ["hill_tan_reduced", "hill_tan_full", "fan2014", "gray_thornton", "liu_henann"]
)
def test_adversarial_random_fields_stay_bounded(model: str) -> None:
    """Random S, γ̇, φ (including 0 and 1), positions partly outside the grid: bounded, conserved."""
    rng = np.random.default_rng(11)
    prm = make_params(
        model,
        b_c_small=-0.5,
        gravity_xy=(G * np.sin(SLOPE), -G * np.cos(SLOPE)),
        diffusivity=0.0,
        q=0.05,
    )
    for case in range(60):
        periodic = case % 2
        n = int(rng.integers(5, 300))
        px, py, vol0, phi, cg = _random_case(rng, periodic, n)
        px += rng.normal(0.0, 1e-3, n)  # some points leave the region: clamped/wrapped weights
        py += rng.normal(0.0, 1e-3, n)
        phi = rng.choice([0.0, 1.0, 0.5, 1e-12, 1 - 1e-12], n) * (rng.uniform(0, 1, n) < 0.5)
        phi += (phi == 0.0) * rng.uniform(0.0, 1.0, n) * (rng.uniform(0, 1, n) < 0.5)
        work = allocate_work(cg)
        total0 = np.dot(vol0, phi)
        t_int = 10 ** rng.uniform(-4, -1.5)
        for _ in range(3):
            s_int = rng.normal(0.0, 1.0, n) * 10 ** rng.uniform(-2, 0.5) * t_int
            g_int = rng.uniform(0.0, 50.0, n) * t_int
            concentration_step(px, py, vol0, phi, s_int, g_int, t_int, cg, prm, work)
            assert np.all(phi >= 0.0) and np.all(phi <= 1.0)
            assert abs(np.dot(vol0, phi) - total0) <= 1e-12 * max(total0, vol0.sum())


def test_none_model_and_zero_interval_do_nothing() -> None:
    px, py, vol0 = strip_layout(0.002, 0.002, 0.25e-3)
    cg = make_conc_grid(0.0, 0.002, 0.0, 0.002, 0.25e-3, 1)
    work = allocate_work(cg)
    phi = np.linspace(0.0, 1.0, px.size)
    s_int = np.linspace(0.0, 1.0, px.size)
    g_int = s_int.copy()
    n = concentration_step(px, py, vol0, phi, s_int, g_int, 1e-3, cg, make_params("none"), work)
    assert n == 0 and not s_int.any() and not g_int.any()
    assert np.array_equal(phi, np.linspace(0.0, 1.0, px.size))
    s_int[:] = 1.0
    n = concentration_step(px, py, vol0, phi, s_int, g_int, 0.0, cg, make_params(), work)
    assert n == 0 and not s_int.any()


def test_make_conc_grid_geometry() -> None:
    cg = make_conc_grid(0.0, 0.012, 0.0, 0.01, 0.25e-3, True)
    assert isinstance(cg, ConcGrid)
    assert cg.ncx == 48 and cg.periodic_x == 1 and cg.x0 == 0.0
    assert cg.ncy == 42 and cg.y0 == pytest.approx(-0.25e-3)  # 40 cells + 2 ghost rows
    cg2 = make_conc_grid(0.0, 0.02, 0.0, 0.04, 0.5e-3, False)
    assert cg2.ncx == 42 and cg2.x0 == pytest.approx(-0.5e-3)
    with pytest.raises(ValueError, match="whole number"):
        make_conc_grid(0.0, 0.0121, 0.0, 0.01, 0.25e-3, True)
    work = allocate_work(cg)
    # the engine's scratch: its rows C_* on the grid's cells (one layer in z)
    assert work.shape[1:] == (48, 42, 1) and work.dtype == np.float64


def test_tent_weights_partition_of_unity() -> None:
    rng = np.random.default_rng(3)
    for x in rng.uniform(-0.01, 0.03, 200):
        for periodic in (0, 1):
            i0, i1, w0, w1 = tent_weights(x, 0.0, 1e-3, 12, periodic)
            assert w0 + w1 == pytest.approx(1.0, abs=1e-15)
            assert 0 <= i0 < 12 and 0 <= i1 < 12 and w0 >= 0.0 and w1 >= 0.0
            if periodic:
                centre = (i0 + 0.5) * 1e-3
                d = (x - centre) % 0.012
                assert w1 == pytest.approx(d / 1e-3, abs=1e-9)


def test_pack_params_from_config() -> None:
    config = pytest.importorskip("segmpm.config")
    cfg = config.load_config(
        preset="chute_seed", overrides=["segregation.model=fan2014", "segregation.dt=0.002"]
    )
    g = (G * np.sin(SLOPE), -G * np.cos(SLOPE))
    prm = pack_params(cfg, g)
    assert prm.shape == (N_PARAMS,) and prm.dtype == np.float64
    assert prm[P_MODEL] == MODEL_CODES["fan2014"]
    assert prm[P_DT_TARGET] == 0.002
    assert prm[P_RHO_BULK] == pytest.approx(
        cfg.material.solid_fraction * cfg.material.grain_density
    )
    assert prm[P_GX] == g[0] and prm[P_GY] == g[1]
    assert prm[P_HC] == pytest.approx(0.5 * cfg.grid.cell_size)
