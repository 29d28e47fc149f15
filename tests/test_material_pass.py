"""The material pass of the generic engine's time loop (``update_stress`` of
``segmpm.engine.codegen.for_material(dim, mat)``: blocks of points, the law a compile-time
constant, a vectorised update loop and a scalar reduction per block) against the NumPy references
of the models, point by point, in 2-D and 3-D: gas points, points on the yield cap, every
segregation driver (A, B, C, P, G), b ≠ 1, bulk viscosity, the linear elastic model, the nonlocal
rheology, a partial last block, failing points (the first in index order, a non-finite state
before a point that left the grid), the output diagnostics written only when asked, and results
independent of the thread count.

References: in 2-D the plane-strain point laws of :mod:`segmpm.materials`
(``material_update_np``, tensors ``xx, yy, xy, zz``); in 3-D the full-matrix laws of
:mod:`segmpm.engine.reference` and, for linear elasticity, :func:`_hooke_np` below.
tests/test_engine.py::test_material_pass_is_the_point_law_at_every_point checks the same pass for
three laws against the 3-D references; this file covers the eight cases the former plane-strain pass was tested on."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from segmpm.config import load_config
from segmpm.engine.codegen import for_material
from segmpm.engine.records import XX, XY, YY, ZZ, Points, material_record
from segmpm.engine.reference import fei_tensor_np, mat_to_sym, ngf_tensor_np, sym_to_mat
from segmpm.materials import (
    KIND_FEI2016,
    KIND_FEI2016_NGF,
    KIND_LINEAR_ELASTIC,
    material_update_np,
    pack_material,
)
from segmpm.materials.params import M_CAPR, M_F, M_KIND, M_LAMBDA, M_MU, M_RHO_S

# the status codes of the loop
from segmpm.mpm.params import ST_LEFT_GRID, ST_NONFINITE, ST_OK

CASES = {
    "fei-b1-driverB": [],
    "fei-b1-driverA-bulk": ["segregation.driver='A'", "material.bulk_viscosity=0.1"],
    "fei-power-driverC": ["material.b=0.7", "segregation.driver='C'"],
    "linear-elastic": ["material.model='linear_elastic'"],
    "fei-b1-driverP": ["segregation.model='liu_henann'"],
    "nonlocal-driverG": [
        "material.rheology='nonlocal'",
        "material.q_phi=0.6",
        "segregation.model='hill_tan_fluidity'",
    ],  # fmt: skip
    "nonlocal-driverP-bulk": [
        "material.rheology='nonlocal'",
        "material.q_phi=0.6",
        "segregation.model='liu_henann'",
        "material.bulk_viscosity=0.1",
    ],
    "nonlocal-driverA": [
        "material.rheology='nonlocal'",
        "material.q_phi=0.6",
        "segregation.driver='A'",
    ],  # fmt: skip
}
DT = 1e-5
#: the twin's tensor rows (xx, yy, xy, zz) as rows of the generic engine's (xx, yy, zz, xy)
TO_2D = [XX, YY, XY, ZZ]
#: the generic engine's rows (xx, yy, zz, xy) as rows of the twin's
FROM_2D = [0, 1, 3, 2]


def _material(overrides):
    """The packed record (as the builders pack it; it does not depend on the dimension)."""
    mp = pack_material(
        load_config(preset="chute_seed", overrides=["material.stiffness_scale=1e-2", *overrides])
    )
    return mp, material_record(mp)


def _inputs(overrides, dim, rng):
    """Random points for the pass (3 blocks and a partial one): velocity gradients of ~20/s,
    elastic strains of ~3e-4 about a volumetric strain I₁ ∈ (−1e-4, 1e-3) (so about a tenth of
    the points are gas, I₁ ≤ 0), and the compiled pass's kernels."""
    mp, mat = _material(overrides)
    k = for_material(dim, mat)
    n = 3 * k.BLOCK + 37
    ne = k.NE
    L = np.zeros((n, 3, 3))
    L[:, :dim, :dim] = rng.normal(scale=20.0, size=(n, dim, dim))
    I1 = rng.uniform(-1e-4, 1e-3, n)
    e = np.zeros((n, 6))  # engine order xx, yy, zz, xy, xz, yz
    e[:, :ne] = rng.normal(scale=3e-4, size=(n, ne))
    e[:, :3] -= I1[:, None] / 3
    J = np.exp(-I1)
    arrays = {
        "x": rng.uniform(0.0, 0.01, (dim, n)),
        "v": rng.normal(scale=0.3, size=(dim, n)),
        "C": np.zeros((dim * dim, n)),
        "mass": np.ones(n),
        "vol0": np.ones(n),
        "J": J,
        "eps": np.ascontiguousarray(e[:, :ne].T),
        "sig": np.zeros((ne, n)),
        "phi": rng.uniform(0, 1, n),
        # fluidity, 1/s: up to the order of 1/Δt of the return (the nonlocal flow rule)
        "gf": rng.uniform(0, 2e3, n),
        "diag": np.full((6, n), -7.0),  # a sentinel: rows 1-5 are written only when asked
        "s_int": rng.uniform(0, 1e-3, n),
        "g_int": rng.uniform(0, 1e-3, n),
        "lg": np.ascontiguousarray(L[:, :dim, :dim].reshape(n, dim * dim).T),
        "flags": np.zeros(n, dtype=np.int8),
        "cursor": np.zeros(n, dtype=np.int32),
        "x_old": np.zeros((dim, 0)),
    }
    return mp, mat, k, L, e, arrays


def _run(k, mat, a, full, threads=1):
    """The pass on copies of the arrays ``a``; returns (status, point, smax, numax), arrays."""
    out = {f: v.copy() for f, v in a.items()}
    r = k.update_stress(Points(**out), mat, DT, full, threads)
    return r, out


def _hooke_np(mp, L, e, J, dt):
    """3-D linear (Hooke) elasticity with the Jaumann predictor, full matrices: the reference of
    the engine's elastic law (σ = λ tr ε 1 + 2 μ ε, p = −tr σ/3, c = √((λ + 2μ)/ρ))."""
    eye = np.eye(3)
    d = 0.5 * (L + np.swapaxes(L, 1, 2))
    w = 0.5 * (L - np.swapaxes(L, 1, 2))
    E = sym_to_mat(e)
    E = E + dt * (d + w @ E - E @ w)
    lam, mu = mp[M_LAMBDA], mp[M_MU]
    tr = np.trace(E, axis1=1, axis2=2)
    sig = lam * tr[:, None, None] * eye + 2 * mu * E
    dp = d - np.trace(d, axis1=1, axis2=2)[:, None, None] / 3 * eye
    z = np.zeros_like(J)
    return {"eps": mat_to_sym(E), "sig": mat_to_sym(sig), "pe": -np.trace(sig, axis1=1, axis2=2) / 3,
            "gdot": np.sqrt(2 * np.einsum("nij,nij->n", dp, dp)), "inertial": z, "S": z,
            "c": np.sqrt((lam + 2 * mu) / (mp[M_F] * mp[M_RHO_S] / J)), "nu": z}  # fmt: skip


def _reference(mp, mat, dim, L, e, J, phi, gf):
    """The NumPy reference at every point: new ε, σ (engine rows, (NE, n)), p_e, γ̇, I, S, c, ν."""
    ne = 4 if dim == 2 else 6
    if dim == 2:
        eps, sig, p, gdot, inertial, S, c, nu = material_update_np(
            mp, L[:, :2, :2], DT, e[:, TO_2D], J, phi, gf
        )
        return eps[:, FROM_2D].T, sig[:, FROM_2D].T, p, gdot, inertial, S, c, nu
    if mp[M_KIND] == KIND_FEI2016_NGF:
        r = ngf_tensor_np(mat[0], L, e, J, phi, gf, DT)
    elif mp[M_KIND] == KIND_FEI2016:
        r = fei_tensor_np(mat[0], L, e, J, phi, DT)
    else:
        assert mp[M_KIND] == KIND_LINEAR_ELASTIC
        r = _hooke_np(mp, L, e, J, DT)
    return (r["eps"][:, :ne].T, r["sig"][:, :ne].T,
            *(r[q] for q in ("pe", "gdot", "inertial", "S", "c", "nu")))  # fmt: skip


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("case", sorted(CASES))
def test_material_pass_matches_reference(case, dim, rng):
    """At every point the pass gives the reference's strain, stress and diagnostics (p_e, γ̇, I,
    S, c + |v|, ν) and the subcycle integrals ∫S dt, ∫γ̇ dt, to round-off (1e-10 relative per
    point: the pass contracts products into FMAs, the references evaluate full matrices in
    another order; the nonlocal references find the return factor by bisection to ~1e-15); the
    reductions are the stored maxima exactly; without the output diagnostics the same state with
    rows 1-5 of ``diag`` untouched."""
    mp, mat, k, L, e, a = _inputs(CASES[case], dim, rng)
    J = a["J"]
    n = J.size
    # the sample covers the gas state and, for the granular model, the yield cap
    I1 = -np.log(J)
    assert np.sum(I1 <= 0) > 50
    if "elastic" not in case:
        dev = e[:, :3] - e[:, :3].mean(axis=1, keepdims=True)
        I2 = 0.5 * (np.sum(dev**2, axis=1) + 2 * np.sum(e[:, 3:] ** 2, axis=1))
        assert np.sum((I1 > 0) & (np.sqrt(I2) > mp[M_CAPR] * I1)) > 50
    (status, idx, smax, numax), out = _run(k, mat, a, True)
    assert status == ST_OK and idx == -1
    e_ref, s_ref, p_ref, g_ref, i_ref, S_ref, c_ref, nu_ref = _reference(
        mp, mat, dim, L, e, J, a["phi"], a["gf"]
    )
    assert e_ref.shape == out["eps"].shape == (k.NE, n)
    np.testing.assert_allclose(out["eps"], e_ref, rtol=1e-10, atol=1e-16)
    np.testing.assert_allclose(out["sig"], s_ref, rtol=1e-10, atol=1e-9)
    speed = c_ref + np.sqrt(np.sum(a["v"] ** 2, axis=0))
    for row, ref, atol in ((0, p_ref, 1e-9), (1, g_ref, 1e-12), (2, i_ref, 1e-12),
                           (3, S_ref, 1e-12), (4, speed, 1e-12), (5, nu_ref, 1e-16)):  # fmt: skip
        np.testing.assert_allclose(out["diag"][row], ref, rtol=1e-10, atol=atol, err_msg=row)
    np.testing.assert_allclose(out["s_int"] - a["s_int"], S_ref * DT, rtol=1e-10, atol=1e-20)
    np.testing.assert_allclose(out["g_int"] - a["g_int"], g_ref * DT, rtol=1e-10, atol=1e-20)
    # the reductions are those of the stored diagnostics, exactly
    assert smax == out["diag"][4].max() and numax == out["diag"][5].max()
    # the pass did something: stresses, and (granular laws) a segregation driver somewhere
    assert np.abs(out["sig"]).max() > 0
    if "elastic" not in case and "driverC" not in case:
        assert np.abs(S_ref).max() > 0

    # without the output diagnostics: the same state, rows 1-5 untouched
    (status2, _, smax2, numax2), out2 = _run(k, mat, a, False)
    assert status2 == ST_OK and smax2 == smax and numax2 == numax
    for f in ("eps", "sig", "J", "s_int", "g_int"):
        np.testing.assert_array_equal(out2[f], out[f], err_msg=f)
    np.testing.assert_array_equal(out2["diag"][0], out["diag"][0])
    assert np.all(out2["diag"][1:] == -7.0)


@pytest.mark.parametrize("dim", [2, 3])
def test_failing_points_first_in_index_order(dim, rng):
    """The pass reports the first failing point in index order, across blocks: a non-finite
    velocity gradient (so a non-finite stress: ST_NONFINITE) before two points flagged as having
    left the grid (ST_LEFT_GRID, one in the partial last block); the failing points'
    diagnostics are written even without the output diagnostics, the others' not. With the
    gradient made finite, the first point that left the grid is reported."""
    _, mat, k, _, _, a = _inputs([], dim, rng)
    n = a["J"].size
    k_nan, k_out = k.BLOCK + 3, 2 * k.BLOCK + 5
    a["lg"][0, k_nan] = np.nan
    a["flags"][k_out] = ST_LEFT_GRID
    a["flags"][n - 1] = ST_LEFT_GRID  # the partial last block
    (status, idx, _, _), out = _run(k, mat, a, False)
    assert status == ST_NONFINITE and idx == k_nan
    bad = np.zeros(n, dtype=bool)
    bad[[k_nan, k_out, n - 1]] = True
    assert np.all(out["diag"][1:, ~bad] == -7.0)
    assert np.all(out["diag"][4, [k_out, n - 1]] != -7.0)
    a["lg"][0, k_nan] = 1.0
    (status, idx, _, _), _ = _run(k, mat, a, False)
    assert status == ST_LEFT_GRID and idx == k_out


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("case", ["fei-b1-driverB", "nonlocal-driverG"])
def test_material_pass_does_not_depend_on_thread_count(case, dim, rng):
    """One and two threads (and the block sizes they set) give bit-identical states, diagnostics
    and reductions."""
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("needs at least 2 numba threads")
    _, mat, k, _, _, a = _inputs(CASES[case], dim, rng)
    runs = []
    before = numba.get_num_threads()
    for threads in (1, 2):
        numba.set_num_threads(threads)
        try:
            runs.append(_run(k, mat, a, True, threads))
        finally:
            numba.set_num_threads(before)  # the suite's setting (conftest)
    assert runs[0][0] == runs[1][0] and runs[0][0][0] == ST_OK
    for f in runs[0][1]:
        np.testing.assert_array_equal(runs[0][1][f], runs[1][1][f], err_msg=f)
