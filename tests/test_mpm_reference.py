"""The compiled loop agrees with the plain NumPy reference of one step (APIC, USL)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import make_sim as _make_sim

from segmpm.mpm.reference import step_np
from segmpm.mpm.shape import bspline2, bspline2_np
from segmpm.state import STATE_ARRAYS


def make_sim(overrides: list[str], *args, **kw):
    """These are the production plane-strain engine's own tests (grid.engine = "production",
    kept until that engine is removed); the default engine's are in tests/test_engine.py."""
    return _make_sim([*overrides, "grid.engine='production'"], *args, **kw)


CASES = {
    "chute-fei": ["geometry.length=0.003", "geometry.depth=0.004", "material.stiffness_scale=1e-3"],
    "chute-fei-apic": ["geometry.length=0.003", "geometry.depth=0.004", "grid.transfer='apic'",
                       "material.stiffness_scale=1e-3", "boundary.ramp_time=0.1"],
    "chute-slip-elastic": [
        "geometry.length=0.003", "geometry.depth=0.004", "material.model='linear_elastic'",
        "boundary.base='friction'", "boundary.base_friction=0.3",
    ],
    "chute-nonlocal-rate-wall": [
        "geometry.length=0.003", "geometry.depth=0.004", "material.stiffness_scale=1e-3",
        "material.rheology='nonlocal'", "material.q_phi=0.6", "material.fluidity_dt=1e-9",
        "boundary.sidewall_friction_slow=0.1", "boundary.sidewall_slip_speed=0.05",
        "segregation.model='liu_henann'",
    ],
    "collapse-friction-walls": [
        "scenario.kind='collapse'", "geometry.length=0.006", "geometry.column_width=0.003",
        "geometry.column_height=0.004", "boundary.walls='friction'", "geometry.slope_deg=10",
        "material.stiffness_scale=1e-3",
    ],
}  # fmt: skip


@pytest.mark.parametrize("case", sorted(CASES))
def test_one_step_matches_numpy_reference(case, rng):
    sim = make_sim(CASES[case])
    sim._prime()
    st = sim.state
    # a non-trivial state: random velocities and affine fields, some shear already in the strain
    st.v[:] = rng.normal(scale=0.05, size=st.v.shape)
    st.v[1] = np.where(
        st.x[1] < 0.001, np.abs(st.v[1]) * -1, st.v[1]
    )  # some points push on the base
    st.C[:] = rng.normal(scale=5.0, size=st.C.shape)
    st.eps[2] += rng.normal(scale=1e-6, size=st.n)
    st.phi[:] = rng.uniform(0, 1, st.n)
    st.gf[:] = rng.uniform(0, 50, st.n)  # the fluidity (read by the nonlocal case only)
    sim._primed = False
    st.sc[1] = 0  # re-prime the stresses from the perturbed strain
    sim._prime()
    before = {k: v.copy() for k, v in st.arrays().items()}
    ref = step_np(before, st.gp, st.mp)
    status, _, n = sim.advance(1.0, 1)
    assert status == 0 and n == 1
    for k in (*STATE_ARRAYS, "sc"):
        a, b = getattr(st, k), ref[k]
        scale = max(np.max(np.abs(b)), 1e-300)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-11 * scale, err_msg=k)
    # the step did something: points moved and stresses changed
    assert np.max(np.abs(st.x - before["x"])) > 0
    assert np.max(np.abs(st.sig - before["sig"])) > 0


def test_bspline_partition_of_unity_and_reference(rng):
    xi = rng.uniform(-5, 50, 1000)
    base, w, d = bspline2_np(xi)
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-14)
    np.testing.assert_allclose(d.sum(axis=1), 0.0, atol=1e-13)
    # the first moment is reproduced: Σ w_i ξ_i = ξ (linear completeness)
    nodes = base[:, None] + np.arange(3)
    np.testing.assert_allclose((w * nodes).sum(axis=1), xi, atol=1e-12)
    np.testing.assert_allclose((d * nodes).sum(axis=1), 1.0, atol=1e-12)
    for i in range(0, 1000, 97):
        r = bspline2(xi[i])
        assert r[0] == base[i]
        np.testing.assert_allclose(r[1:4], w[i], atol=1e-15)
        np.testing.assert_allclose(r[4:7], d[i], atol=1e-15)
