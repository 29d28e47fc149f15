"""The material pass of the time loop (``update_stress``: blocks of points, a vectorised update
loop and a scalar reduction per block) against the NumPy reference of the models, point by point:
gas points, points on the yield cap, every segregation driver, b ≠ 1, the linear elastic model,
a partial last block, failing points, and the output diagnostics written only when asked."""

from __future__ import annotations

import numba
import numpy as np
import pytest

from segmpm.config import load_config
from segmpm.materials import material_update_np, pack_material
from segmpm.materials.params import M_CAPR
from segmpm.mpm import step as S
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
#: a partial last block
N = 3 * S.BLOCK + 37
DT = 1e-5


def _inputs(overrides, rng):
    prm = pack_material(
        load_config(preset="chute_seed", overrides=["material.stiffness_scale=1e-2", *overrides])
    )
    L = rng.normal(scale=20.0, size=(N, 2, 2))
    I1 = rng.uniform(-1e-4, 1e-3, N)
    eps = rng.normal(scale=3e-4, size=(N, 4))
    eps[:, [0, 1, 3]] -= I1[:, None] / 3
    J = np.exp(-I1)
    arrays = {
        "x": rng.uniform(0.0, 0.01, (2, N)),
        "v": rng.normal(scale=0.3, size=(2, N)),
        "J": J,
        "eps": np.ascontiguousarray(eps.T),
        "sig": np.zeros((4, N)),
        "phi": rng.uniform(0, 1, N),
        # fluidity, 1/s: up to the order of 1/Δt of the return (the nonlocal flow rule)
        "gf": rng.uniform(0, 2e3, N),
        "diag": np.full((6, N), -7.0),  # a sentinel: rows 1-5 are written only when asked
        "s_int": rng.uniform(0, 1e-3, N),
        "g_int": rng.uniform(0, 1e-3, N),
        "flags": np.zeros(N, dtype=np.int8),
        "lg": np.ascontiguousarray(
            np.stack([L[:, 0, 0], L[:, 0, 1], L[:, 1, 0], L[:, 1, 1], -np.log(J)])
        ),
    }
    return prm, L, eps, J, arrays


def _run(prm, a, full):
    out = {k: v.copy() for k, v in a.items()}
    r = S.update_stress(out["x"], out["v"], out["J"], out["eps"], out["sig"], out["phi"],
                        out["gf"], out["diag"], out["s_int"], out["g_int"], prm, DT, out["flags"], out["lg"],
                        full, numba.get_num_threads())  # fmt: skip
    return r, out


@pytest.mark.parametrize("case", sorted(CASES))
def test_material_pass_matches_reference(case, rng):
    prm, L, eps, J, a = _inputs(CASES[case], rng)
    # the sample covers the gas state and, for the granular model, the yield cap
    I1 = -np.log(J)
    assert np.sum(I1 <= 0) > 50
    if "elastic" not in case:
        trial = eps.copy()
        dev = trial[:, [0, 1, 3]] - trial[:, [0, 1, 3]].mean(axis=1, keepdims=True)
        I2 = 0.5 * (np.sum(dev**2, axis=1) + 2 * trial[:, 2] ** 2)
        assert np.sum((I1 > 0) & (np.sqrt(I2) > prm[M_CAPR] * I1)) > 50
    (status, idx, smax, numax), out = _run(prm, a, True)
    assert status == ST_OK and idx == -1
    e_ref, s_ref, p_ref, g_ref, i_ref, S_ref, c_ref, nu_ref = material_update_np(
        prm, L, DT, eps, J, a["phi"], a["gf"]
    )
    np.testing.assert_allclose(out["eps"].T, e_ref, rtol=1e-10, atol=1e-16)
    np.testing.assert_allclose(out["sig"].T, s_ref, rtol=1e-10, atol=1e-9)
    speed = c_ref + np.hypot(a["v"][0], a["v"][1])
    for row, ref, atol in ((0, p_ref, 1e-9), (1, g_ref, 1e-12), (2, i_ref, 1e-12),
                           (3, S_ref, 1e-12), (4, speed, 1e-12), (5, nu_ref, 1e-16)):  # fmt: skip
        np.testing.assert_allclose(out["diag"][row], ref, rtol=1e-10, atol=atol, err_msg=row)
    np.testing.assert_allclose(out["s_int"] - a["s_int"], S_ref * DT, rtol=1e-10, atol=1e-20)
    np.testing.assert_allclose(out["g_int"] - a["g_int"], g_ref * DT, rtol=1e-10, atol=1e-20)
    # the reductions are those of the stored diagnostics, exactly
    assert smax == out["diag"][4].max() and numax == out["diag"][5].max()

    # without the output diagnostics: the same state, rows 1-5 untouched
    (status2, _, smax2, numax2), out2 = _run(prm, a, False)
    assert status2 == ST_OK and smax2 == smax and numax2 == numax
    for k in ("eps", "sig", "J", "s_int", "g_int"):
        np.testing.assert_array_equal(out2[k], out[k], err_msg=k)
    np.testing.assert_array_equal(out2["diag"][0], out["diag"][0])
    assert np.all(out2["diag"][1:] == -7.0)


def test_failing_points_first_in_index_order(rng):
    prm, _, _, _, a = _inputs([], rng)
    k_nan, k_out = S.BLOCK + 3, 2 * S.BLOCK + 5
    a["lg"][0, k_nan] = np.nan  # a non-finite velocity gradient: a non-finite stress
    a["flags"][k_out] = ST_LEFT_GRID
    a["flags"][N - 1] = ST_LEFT_GRID  # the partial last block
    (status, idx, _, _), out = _run(prm, a, False)
    assert status == ST_NONFINITE and idx == k_nan
    # the failing points' diagnostics are written even without the output diagnostics
    bad = np.zeros(N, dtype=bool)
    bad[[k_nan, k_out, N - 1]] = True
    assert np.all(out["diag"][1:, ~bad] == -7.0)
    assert np.all(out["diag"][4, [k_out, N - 1]] != -7.0)
    a["lg"][0, k_nan] = 1.0
    (status, idx, _, _), _ = _run(prm, a, False)
    assert status == ST_LEFT_GRID and idx == k_out


def test_material_pass_does_not_depend_on_thread_count(rng):
    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("needs at least 2 numba threads")
    prm, _, _, _, a = _inputs([], rng)
    runs = []
    for threads in (1, 2):
        numba.set_num_threads(threads)
        try:
            runs.append(_run(prm, a, True))
        finally:
            numba.set_num_threads(1)
    assert runs[0][0] == runs[1][0]
    for k in runs[0][1]:
        np.testing.assert_array_equal(runs[0][1][k], runs[1][1][k], err_msg=k)
