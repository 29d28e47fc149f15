"""MPM core verification on the generic 2-D engine: the clamped elastic bar against its closed
form (period within 1 %, second-order convergence in h, APIC energy drift), and the P2G counting
sort shared by the kernels.

Closed forms: docs/model.md §3; boundaries and transfers: docs/model.md §2. The other
verification bodies of the generic engine are in tests/test_engine.py, in 2-D and 3-D: free fall
(``test_generic_box_free_fall_is_exact``), momentum and P2G mass of the periodic box
(``test_generic_periodic_box_conserves_momentum_and_p2g_mass_is_exact``), the periodic wrap
(``test_generic_points_wrap_across_the_periodic_boundary``), the periodic wave's second order
(``test_generic_periodic_wave_period_is_second_order``) and the 3-D bar's convergence
(``test_3d_bar_period_converges_to_the_closed_form``).
"""

from __future__ import annotations

import math

import numba
import numpy as np
import pytest
from conftest import make_sim

# the parallel counting sort of P2G (not specialised by dimension)
from segmpm.engine.helpers import counting_sort
from segmpm.engine.records import XX, XY, YY, ZZ

BAR_E, BAR_RHO, BAR_L, BAR_V0 = 100.0, 1.0, 1.0, 0.01
BAR_C = math.sqrt(BAR_E / BAR_RHO)
BAR_PERIOD = 4 * BAR_L / BAR_C  # ω₁ = (π/2L) √(E/ρ)


def bar_sim(cells: int, transfer: str = "apic"):
    """The bar of docs/model.md §3 (ν = 0, clamped at x = 0 with image nodes, free at x = L,
    first mode v₀ sin(πx/2L)) on the generic 2-D engine, one cell deep."""
    h = BAR_L / cells
    sim = make_sim([
        "scenario.kind='bar'", "material.model='linear_elastic'",
        f"material.youngs_modulus={BAR_E}", "material.poisson_ratio=0.0",
        "material.solid_fraction=1.0", f"material.grain_density={BAR_RHO}",
        f"geometry.length={BAR_L}", f"geometry.depth={h}", f"grid.cell_size={h}",
        "geometry.headroom=0.2", f"scenario.velocity={BAR_V0}", "time.cfl=0.2",
        f"grid.transfer='{transfer}'", "segregation.model='none'",
    ])  # fmt: skip
    assert sim.dim == 2
    return sim


def bar_history(sim, periods: float, samples_per_period: int = 200):
    """Times, centre-of-mass velocity and total (kinetic + stored elastic) energy."""
    P = sim.engine.points
    ts, vcm, energy = [], [], []
    M = P.mass.sum()
    for k in range(int(periods * samples_per_period) + 1):
        sim.advance_to(k * BAR_PERIOD / samples_per_period)
        ts.append(sim.time)
        vcm.append(np.sum(P.mass * P.v[0]) / M)
        vol = P.vol0 * P.J
        ke = 0.5 * np.sum(P.mass * (P.v[0] ** 2 + P.v[1] ** 2))
        se = 0.5 * np.sum(vol * (P.sig[XX] * P.eps[XX] + P.sig[YY] * P.eps[YY]
                                 + P.sig[ZZ] * P.eps[ZZ] + 2 * P.sig[XY] * P.eps[XY]))  # fmt: skip
        energy.append(ke + se)
    return np.array(ts), np.array(vcm), np.array(energy)


def measured_period(ts, v):
    """Twice the mean spacing of the linearly interpolated sign changes of v(t)."""
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
    """At the default resolution (64 cells) the measured period of the first mode is the
    closed form 4L/√(E/ρ) within 1 %, and the centre-of-mass velocity swings with the mode's
    amplitude 2v₀/π within 2 %."""
    ts, v, _ = bar_runs[BAR_DEFAULT_CELLS]
    err = abs(measured_period(ts, v) - BAR_PERIOD) / BAR_PERIOD
    assert err < 0.01, err
    assert abs(np.max(np.abs(v)) - 2 * BAR_V0 / np.pi) < 0.02 * 2 * BAR_V0 / np.pi


def test_bar_period_converges_with_refinement(bar_runs):
    """Second order in h, like the interior scheme (the periodic wave of tests/test_engine.py),
    because the clamped end has image nodes (docs/model.md, "No-slip walls"). With plain fixed
    nodes the one-sided B-spline basis at the clamp made it first order (4.2, 2.1, 1.0, 0.49 %
    at 8–64 cells)."""
    errs = {c: abs(measured_period(*bar_runs[c][:2]) - BAR_PERIOD) / BAR_PERIOD for c in bar_runs}
    order = math.log(errs[16] / errs[BAR_DEFAULT_CELLS]) / math.log(BAR_DEFAULT_CELLS / 16)
    assert errs[16] > errs[32] > errs[BAR_DEFAULT_CELLS]
    assert 1.7 < order < 2.3, (errs, order)


def test_bar_apic_energy_drift_bounded(bar_runs):
    """APIC is nearly conservative: the total energy of the free vibration drifts by less than
    2 % over 10 periods (64 cells)."""
    _, _, e = bar_runs[BAR_DEFAULT_CELLS]
    assert e[0] > 0
    drift = np.max(np.abs(e - e[0])) / e[0]
    assert drift < 0.02, drift


@pytest.mark.parametrize(("threads", "chunks"), [(1, 1), (1, 3), (2, 2), (2, 5)])
def test_counting_sort_is_the_stable_sort(threads, chunks):
    """The parallel counting sort by slab gives NumPy's stable argsort and the slab offsets,
    whatever the number of threads and chunks."""
    if threads > numba.config.NUMBA_NUM_THREADS:
        pytest.skip("needs two threads")
    rng = np.random.default_rng(3)
    ns = 37
    cursor = rng.integers(0, ns, 50_001).astype(np.int32)
    cursor[:5000] = 7  # a long run of one slab across a chunk boundary
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
