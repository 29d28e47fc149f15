"""One step of the generic 2-D engine (``segmpm.engine``, D = 2) agrees with the plain NumPy
twin of the 2-D step (``step_np``: APIC/AFLIP, USL), and the B-spline shape functions with their
NumPy reference.

The twin reads the 2-D state layout of ``segmpm.mpm.reference`` (tensors ``xx, yy, xy, zz``, the
scalar slots ``S_*``, the grid record ``G_*``); the generic records are translated into it here
(``_twin_state``, ``_twin_params``) and the twin's result back (``TO_TWIN``)."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import make_sim

from segmpm.engine.records import XX, XY, YY, ZZ
from segmpm.engine.shape import bspline2, bspline2_np

# the twin's record slots (G_*, S_*, BC_*), the NumPy twin of one step, and the NumPy/compiled
# quadratic B-spline
from segmpm.mpm import params as mpp
from segmpm.mpm.reference import step_np

#: the twin's tensor rows (xx, yy, xy, zz) as rows of the generic engine's (xx, yy, zz, xy)
TO_TWIN = [XX, YY, XY, ZZ]
#: the twin's scalar slots S_* and the generic clock's fields of the same names (lower case)
SLOTS = {getattr(mpp, "S_" + name.upper()): name
         for name in ("time", "step", "tseg", "smax", "numax", "dt", "nseg", "tflu", "nflu")}  # fmt: skip
#: the point arrays the twin reads and writes (rows reordered for the tensors)
POINT_ARRAYS = ("x", "v", "C", "mass", "vol0", "J", "eps", "sig", "phi", "gf", "diag", "s_int",
                "g_int")  # fmt: skip

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


def _twin_params(engine) -> np.ndarray:
    """The twin's grid record ``gp`` (``G_*``) of the generic PARAMS record (2-D): the same
    grid, planes, gravity, sidewall law and time-step control."""
    pr = engine.prm[0]
    assert int(pr["dim"]) == 2 and int(pr["dilatation"]) == 0  # what the twin implements
    # the twin has one Coulomb μ for both x walls
    assert pr["xlo_kind"] != mpp.BC_FRICTION or pr["xlo_mu"] == pr["xhi_mu"]
    gp = np.zeros(mpp.G_NSLOTS)
    gp[mpp.G_X0], gp[mpp.G_Y0] = pr["origin"][0], pr["origin"][1]
    gp[mpp.G_H] = pr["h"]
    gp[mpp.G_NX], gp[mpp.G_NY] = pr["nodes"][0], pr["nodes"][1]
    gp[mpp.G_PERIODIC], gp[mpp.G_LX] = pr["periodic_x"], pr["length_x"]
    gp[mpp.G_BASE_KIND], gp[mpp.G_BASE_Y], gp[mpp.G_BASE_MU] = (pr["base_kind"], pr["base_y"],
                                                                pr["base_mu"])  # fmt: skip
    gp[mpp.G_XLO_KIND], gp[mpp.G_XLO] = pr["xlo_kind"], pr["xlo"]
    gp[mpp.G_XHI_KIND], gp[mpp.G_XHI] = pr["xhi_kind"], pr["xhi"]
    gp[mpp.G_WALL_MU] = pr["xlo_mu"]
    gp[mpp.G_GX], gp[mpp.G_GY] = pr["gravity"][0], pr["gravity"][1]
    gp[mpp.G_SIDEWALL], gp[mpp.G_SW_SLOW] = pr["sidewall"], pr["sidewall_slow"]
    gp[mpp.G_SW_SPEED] = pr["sidewall_speed"]
    gp[mpp.G_RAMP] = pr["ramp"]
    gp[mpp.G_CFL], gp[mpp.G_VISC], gp[mpp.G_CFLOOR] = pr["cfl"], pr["visc"], pr["c_floor"]
    gp[mpp.G_DTMAX], gp[mpp.G_DTMIN] = pr["dt_max"], pr["dt_min"]
    gp[mpp.G_TRANSFER], gp[mpp.G_FLIP] = pr["transfer"], pr["flip"]
    gp[mpp.G_IMAGES] = pr["images"]
    return gp


def _twin_state(sim) -> dict[str, np.ndarray]:
    """Copies of the generic 2-D state in the twin's layout (tensor rows, clock slots)."""
    P = sim.engine.points
    out = {k: getattr(P, k).copy() for k in POINT_ARRAYS}
    out["eps"], out["sig"] = P.eps[TO_TWIN].copy(), P.sig[TO_TWIN].copy()
    out["sc"] = np.zeros(mpp.S_NSLOTS)
    for slot, name in SLOTS.items():
        out["sc"][slot] = sim.clock[name]
    return out


@pytest.mark.parametrize("case", sorted(CASES))
def test_one_step_matches_numpy_reference(case, rng):
    """One step of the generic 2-D kernels from a non-trivial state (random velocities, some
    pushing on the base, random affine fields C, some shear strain, random φ_s and fluidity g,
    the stresses re-derived from the strain by ``prime``) is the NumPy twin's to round-off: every
    point array and every clock slot within 1e-11 of its scale. Cases: the Fei law with AFLIP
    and with APIC during the gravity ramp, linear elasticity on a Coulomb-friction base, the
    nonlocal rheology (with its fluidity update in the step) with the speed-dependent sidewall
    law and liu_henann segregation, and a collapse between frictional walls on a 10° slope."""
    sim = make_sim(CASES[case])
    assert sim.dim == 2
    P = sim.engine.points
    n = sim.engine.n
    P.v[:] = rng.normal(scale=0.05, size=P.v.shape)
    P.v[1] = np.where(P.x[1] < 0.001, -np.abs(P.v[1]), P.v[1])  # some points push on the base
    P.C[:] = rng.normal(scale=5.0, size=P.C.shape)
    P.eps[XY] += rng.normal(scale=1e-6, size=n)
    P.phi[:] = rng.uniform(0, 1, n)
    P.gf[:] = rng.uniform(0, 50, n)  # the fluidity (read by the nonlocal case only)
    sim.prime()  # the stresses, diagnostics and first time step from the perturbed strain
    before = _twin_state(sim)
    ref = step_np(before, _twin_params(sim.engine), sim.engine.mp)
    status, _, steps = sim.advance(1.0, 1)
    assert status == 0 and steps == 1
    after = _twin_state(sim)
    for k in (*POINT_ARRAYS, "sc"):
        a, b = after[k], ref[k]
        scale = max(np.max(np.abs(b)), 1e-300)
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-11 * scale, err_msg=k)
    # the step did something: points moved, stresses changed, the clock advanced
    assert np.max(np.abs(after["x"] - before["x"])) > 0
    assert np.max(np.abs(after["sig"] - before["sig"])) > 0
    assert after["sc"][mpp.S_STEP] == 1 and after["sc"][mpp.S_DT] > 0


def test_bspline_partition_of_unity_and_reference(rng):
    """The quadratic B-spline (NumPy and compiled scalar form): partition of unity, zero sum of
    derivatives, linear completeness, and the two forms agree."""
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
