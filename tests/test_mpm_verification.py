"""MPM core verification: vibrating bar, free fall, conservation, periodic wrap.

Closed forms: docs/model.md §3; boundaries and transfers: docs/model.md §2.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from conftest import make_sim as _make_sim

from segmpm.mpm.transfer import N_MASS, p2g, sort_into_strips


def make_sim(overrides: list[str], *args, **kw):
    """These are the production plane-strain engine's own tests (grid.engine = "production",
    kept until that engine is removed); the default engine's are in tests/test_engine.py."""
    return _make_sim([*overrides, "grid.engine='production'"], *args, **kw)


BAR_E, BAR_RHO, BAR_L = 100.0, 1.0, 1.0
BAR_C = math.sqrt(BAR_E / BAR_RHO)
BAR_PERIOD = 4 * BAR_L / BAR_C  # ω₁ = (π/2L) √(E/ρ)


def bar_sim(cells: int, transfer: str = "apic"):
    h = BAR_L / cells
    return make_sim([
        "scenario.kind='bar'", "material.model='linear_elastic'",
        f"material.youngs_modulus={BAR_E}", "material.poisson_ratio=0.0",
        "material.solid_fraction=1.0", f"material.grain_density={BAR_RHO}",
        f"geometry.length={BAR_L}", f"geometry.depth={h}", f"grid.cell_size={h}",
        "geometry.headroom=0.2", "scenario.velocity=0.01", "time.cfl=0.2",
        f"grid.transfer='{transfer}'",
    ])  # fmt: skip


def bar_history(sim, periods: float, samples_per_period: int = 200):
    st = sim.state
    ts, vcm, energy = [], [], []
    M = st.mass.sum()
    for k in range(int(periods * samples_per_period) + 1):
        t = k * BAR_PERIOD / samples_per_period
        sim.advance_to(t)
        ts.append(sim.time)
        vcm.append(np.sum(st.mass * st.v[0]) / M)
        vol = st.vol0 * st.J
        ke = 0.5 * np.sum(st.mass * (st.v[0] ** 2 + st.v[1] ** 2))
        se = 0.5 * np.sum(vol * (st.sig[0] * st.eps[0] + st.sig[1] * st.eps[1]
                                 + 2 * st.sig[2] * st.eps[2] + st.sig[3] * st.eps[3]))  # fmt: skip
        energy.append(ke + se)
    return np.array(ts), np.array(vcm), np.array(energy)


def measured_period(ts, v):
    s = np.sign(v)
    idx = np.nonzero(s[1:] * s[:-1] < 0)[0]
    zc = ts[idx] - v[idx] * (ts[idx + 1] - ts[idx]) / (v[idx + 1] - v[idx])
    return 2 * np.mean(np.diff(zc))


#: cells along the bar in examples/bar.toml (the default resolution)
BAR_DEFAULT_CELLS = 64


@pytest.fixture(scope="module")
def bar_runs():
    out = {}
    for cells in (16, 32, BAR_DEFAULT_CELLS):
        out[cells] = bar_history(bar_sim(cells), 10 if cells == BAR_DEFAULT_CELLS else 3)
    return out


def test_bar_period_within_one_percent(bar_runs):
    ts, v, _ = bar_runs[BAR_DEFAULT_CELLS]
    err = abs(measured_period(ts, v) - BAR_PERIOD) / BAR_PERIOD
    assert err < 0.01, err
    # and the amplitude of the centre-of-mass velocity is the first mode's 2 v0 / π
    assert abs(np.max(np.abs(v)) - 2 * 0.01 / np.pi) < 0.02 * 2 * 0.01 / np.pi


def test_bar_period_converges_with_refinement(bar_runs):
    """Second order in h, like the interior scheme (periodic wave test below), because the clamped
    end has image nodes (docs/model.md, "No-slip walls"). With plain fixed nodes the one-sided
    B-spline basis at the clamp made it first order (4.2, 2.1, 1.0, 0.49 % at 8–64 cells)."""
    errs = {c: abs(measured_period(*bar_runs[c][:2]) - BAR_PERIOD) / BAR_PERIOD for c in bar_runs}
    order = math.log(errs[16] / errs[BAR_DEFAULT_CELLS]) / math.log(BAR_DEFAULT_CELLS / 16)
    assert errs[16] > errs[32] > errs[BAR_DEFAULT_CELLS]
    assert 1.7 < order < 2.3, (errs, order)


def test_periodic_wave_period_second_order():
    """A standing longitudinal wave in a periodic bar (no boundaries): quadratic B-splines with
    APIC converge at second order in h (docs/model.md §3)."""
    errs = {}
    for cells in (8, 16, 32):
        h = 1.0 / cells
        sim = make_sim([
            "scenario.kind='box'", "material.model='linear_elastic'",
            f"material.youngs_modulus={BAR_E}", "material.poisson_ratio=0",
            "material.solid_fraction=1", f"material.grain_density={BAR_RHO}",
            "geometry.length=1.0", f"geometry.depth={h}", f"grid.cell_size={h}",
            "time.gravity=0", "scenario.velocity=0", "time.cfl=0.2",
        ])  # fmt: skip
        st = sim.state
        st.v[0] = 0.01 * np.sin(2 * np.pi * st.x[0])
        period = 1.0 / BAR_C
        ts, amp = [], []
        for k in range(401):
            sim.advance_to(k * period / 200)
            ts.append(sim.time)
            amp.append(np.sum(st.mass * st.v[0] * np.sin(2 * np.pi * st.x[0])))
        errs[cells] = abs(measured_period(np.array(ts), np.array(amp)) - period) / period
    order = math.log(errs[8] / errs[32]) / math.log(4)
    assert 1.8 < order < 2.3, (errs, order)


def test_bar_apic_energy_drift_bounded(bar_runs):
    ts, v, e = bar_runs[BAR_DEFAULT_CELLS]
    drift = np.max(np.abs(e - e[0])) / e[0]
    # APIC is nearly conservative: less than 2 % of the energy over 10 periods
    assert drift < 0.02, drift


def test_free_fall_exact_kinematics():
    g = 9.81
    sim = make_sim([
        "scenario.kind='box'", "material.model='linear_elastic'", "geometry.slope_deg=0",
        "geometry.length=0.004", "geometry.depth=0.002", "geometry.headroom=3",
        "scenario.velocity=0", "time.dt_max=1e-6", "time.dt_min=1e-9",
    ])  # fmt: skip
    st = sim.state
    y0 = st.x[1].copy()
    n = 200
    status, _, steps = sim.advance(1.0, n)
    assert status == 0 and steps == n
    dt = 1e-6
    t = n * dt
    np.testing.assert_allclose(st.v[1], -g * t, rtol=1e-12)
    np.testing.assert_allclose(st.v[0], 0.0, atol=1e-14)
    # symplectic Euler: y_n = y_0 − g Δt² n(n+1)/2 exactly
    np.testing.assert_allclose(st.x[1], y0 - g * dt * dt * n * (n + 1) / 2, rtol=0, atol=1e-14)
    assert np.max(np.abs(st.sig)) < 1e-9  # stress-free: a uniform motion does not deform
    assert sim.conservation()["mass_drift"] == 0.0


def test_periodic_box_momentum_conserved_and_grid_mass_exact(rng):
    sim = make_sim([
        "scenario.kind='box'", "material.model='linear_elastic'", "time.gravity=0",
        "geometry.length=0.004", "geometry.depth=0.003", "scenario.velocity=0.3",
    ])  # fmt: skip
    st = sim.state
    st.v[:] += rng.normal(scale=0.05, size=st.v.shape)  # a non-uniform motion with stresses
    p0 = np.array([np.sum(st.mass * st.v[0]), np.sum(st.mass * st.v[1])])
    status, _, _ = sim.advance(1.0, 500)
    assert status == 0
    p1 = np.array([np.sum(st.mass * st.v[0]), np.sum(st.mass * st.v[1])])
    scale = np.sum(st.mass * np.hypot(st.v[0], st.v[1]))
    assert np.max(np.abs(p1 - p0)) < 1e-12 * scale
    assert np.max(np.abs(st.sig)) > 0  # the test exercised internal forces
    # P2G distributes the mass exactly (partition of unity)
    w = st.work
    sort_into_strips(st.x[1], st.gp, w["strip_start"], w["cursor"], w["order"])
    p2g(st.x, st.v, st.C, st.mass, st.vol0, st.J, st.sig, st.diag[0], st.gp, w["grid"],
        w["strip_start"], w["order"], np.zeros(3, dtype=np.int64), True)  # fmt: skip
    assert abs(w["grid"][..., N_MASS].sum() - st.mass.sum()) < 1e-14 * st.mass.sum()


def test_points_wrap_across_periodic_boundary():
    L, u = 0.004, 0.5
    sim = make_sim([
        "scenario.kind='box'", "material.model='linear_elastic'", "time.gravity=0",
        f"geometry.length={L}", "geometry.depth=0.002", f"scenario.velocity={u}",
    ])  # fmt: skip
    st = sim.state
    x0 = st.x.copy()
    T = L / u
    for k in range(1, 9):
        sim.advance_to(k * T / 8)
        assert np.all((st.x[0] >= 0) & (st.x[0] < L))
        shift = (x0[0] + u * sim.time) % L
        d = np.abs(st.x[0] - shift)
        assert np.max(np.minimum(d, L - d)) < 1e-12
    np.testing.assert_allclose(st.x[1], x0[1], atol=1e-15)
    d = np.abs(st.x[0] - x0[0])
    assert np.max(np.minimum(d, L - d)) < 1e-12  # back where it started after one period


@pytest.mark.parametrize(("threads", "chunks"), [(1, 1), (1, 3), (2, 2), (2, 5)])
def test_counting_sort_is_the_stable_sort(threads, chunks):
    """The parallel counting sort by strip gives NumPy's stable argsort and the strip offsets,
    whatever the number of threads and chunks."""
    import numba

    from segmpm.mpm.transfer import counting_sort

    if threads > numba.config.NUMBA_NUM_THREADS:
        pytest.skip("needs two threads")
    rng = np.random.default_rng(3)
    ns = 37
    cursor = rng.integers(0, ns, 50_001).astype(np.int32)
    cursor[:5000] = 7  # a long run of one strip across a chunk boundary
    strip_start = np.zeros(ns + 1, dtype=np.int64)
    order = np.full(cursor.size, -1, dtype=np.int32)
    before = numba.get_num_threads()
    numba.set_num_threads(threads)
    try:
        counting_sort(cursor, strip_start, order, chunks)
    finally:
        numba.set_num_threads(before)  # the suite's setting (conftest), not the pool size
    np.testing.assert_array_equal(order, np.argsort(cursor, kind="stable"))
    offsets = np.concatenate([[0], np.cumsum(np.bincount(cursor, minlength=ns))])
    np.testing.assert_array_equal(strip_start, offsets)
