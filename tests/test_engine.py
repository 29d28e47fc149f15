"""The dimension-generic engine (segmpm.engine): code generation, the full-tensor material law
against its NumPy reference and against rotations, P2G against a NumPy reference, the 3-D chute
with frictionless walls against plane strain, resolved Coulomb walls against the sliding-block
closed form, thread independence and resume in 3-D."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from segmpm.config import ConfigError, load_config
from segmpm.engine import codegen
from segmpm.engine.codegen import for_material, kernels
from segmpm.engine.records import PLANE_CODES
from segmpm.engine.reference import fei_tensor_np, mat_to_sym, ngf_tensor_np, p2g_np, sym_to_mat
from segmpm.engine.setup import build

LOCAL3D = [
    "material.rheology='local'",
    "segregation.model='none'",
    "geometry.dimension=3",
    "grid.cell_size=0.001",
    "geometry.length=0.002",
    "output.fields=false",
    "output.figures=false",
    "output.progress=false",
]


def _cfg(extra=(), preset="chute_seed"):
    return load_config(None, [*LOCAL3D, *extra], preset=preset)


def test_codegen_writes_one_file_per_dimension_and_keeps_it():
    k3 = kernels(3)
    k2 = kernels(2)
    assert (k2.D, k2.NE, k2.SZ, k3.D, k3.NE, k3.SZ) == (2, 4, 1, 3, 6, 3)
    path = codegen.generated_dir() / "kernels_d3.py"
    text = path.read_text()
    assert "\nD = 3\n" in text and "\nD = 2\n" not in text
    stamp = path.stat().st_mtime_ns
    codegen._write_if_changed(path, codegen.render(3))  # unchanged text: not rewritten
    assert path.stat().st_mtime_ns == stamp
    with pytest.raises(ValueError):
        codegen.render(4)


def test_the_step_section_is_generated_once_per_law():
    """The material pass and the time loop come in a file per law, with the law a constant,
    and run on the shared kernels of the dimension's file; the record picks the law."""
    head, step = codegen.render(2), codegen.render(2, 3)
    assert "def p2g(" in head and "def advance(" not in head and "def update_stress(" not in head
    assert "def advance(" in step and "def p2g(" not in step and "\nLAW = 3\n" in step
    with pytest.raises(ValueError):
        codegen.render(2, 4)
    laws = {"chute_seed": 1, "chute_nonlocal": 3}  # Fei et al. with b = 1; the fluidity rule
    for preset, law in laws.items():
        small = ["geometry.dimension=3", "grid.cell_size=0.001", "geometry.length=0.002",
                 "geometry.depth=0.006", "geometry.width=0.004"]  # fmt: skip
        mat = build(load_config(None, small, preset=preset), 3).mat
        k = for_material(3, mat)
        assert k.LAW == law and Path(k.__file__).name == f"kernels_d3_law{law}.py"
        assert k.p2g is kernels(3).p2g  # the shared kernels: compiled and cached once


def _random_state(rng, n, dim):
    L = rng.normal(scale=5.0, size=(n, 3, 3))
    if dim == 2:
        L[:, 2, :] = 0.0
        L[:, :, 2] = 0.0
    e = mat_to_sym(sym_to_mat(rng.normal(scale=2e-4, size=(n, 6))))
    e[:, :3] -= 2e-3  # compressed
    if dim == 2:
        e[:, 4:] = 0.0
    J = np.exp(-rng.uniform(5e-4, 5e-3, size=n))
    phi = rng.uniform(0, 1, size=n)
    return L, e, J, phi


def _law_at(k, mat, L, e, J, phi, g, dt):
    """The law at n points through the material pass (``update_stress``, every diagnostic
    written, v = 0, so that row 16 is the wave speed c): rows as ``law`` returns them (ε 6, σ 6,
    p_e, γ̇, I, S, c, ν). The scalar ``material`` entry is not compiled for the tests: it would
    be a second compiled copy of every law (minutes of CI on a fresh cache)."""
    from segmpm.engine.records import Points
    from segmpm.mpm.params import ST_OK

    n, dim, ne = len(J), k.D, k.NE
    P = Points(
        x=np.zeros((dim, n)), v=np.zeros((dim, n)), C=np.zeros((dim * dim, n)), mass=np.ones(n),
        vol0=np.ones(n), J=np.array(J, float), eps=np.asarray(e)[:, :ne].T.copy(),
        sig=np.zeros((ne, n)), phi=np.array(phi, float),
        gf=np.broadcast_to(np.asarray(g, float), (n,)).copy(), diag=np.full((6, n), -7.0),
        s_int=np.zeros(n), g_int=np.zeros(n),
        lg=np.asarray(L)[:, :dim, :dim].reshape(n, dim * dim).T.copy(),
        flags=np.zeros(n, dtype=np.int8), cursor=np.zeros(n, dtype=np.int32),
        x_old=np.zeros((dim, 0)),
    )  # fmt: skip
    status, bad, _, _ = for_material(dim, mat).update_stress(P, mat, dt, True, 1)
    assert (status, bad) == (ST_OK, -1)
    r = np.zeros((n, 18))
    r[:, :ne] = P.eps.T
    r[:, 6 : 6 + ne] = P.sig.T
    r[:, 12:18] = P.diag.T
    return r


@pytest.mark.parametrize("driver", ["A", "B", "C"])
@pytest.mark.parametrize("b", [1.0, 0.7])
def test_tensor_law_matches_numpy_reference(driver, b):
    cfg = _cfg([f"segregation.driver='{driver}'", f"material.b={b}"])
    st = build(cfg, 3)
    k = kernels(3)
    rng = np.random.default_rng(3)
    L, e, J, phi = _random_state(rng, 64, 3)
    J[:4] = np.exp(1e-3)  # gas
    dt = 1e-4
    ref = fei_tensor_np(st.mat[0], L, e, J, phi, dt)
    R = _law_at(k, st.mat, L, e, J, phi, 0.0, dt)
    for p in range(64):
        r = R[p]
        np.testing.assert_allclose(r[0:6], ref["eps"][p], rtol=1e-10, atol=1e-15)
        scale = max(1.0, np.abs(ref["sig"][p]).max())
        np.testing.assert_allclose(r[6:12], ref["sig"][p], rtol=1e-10, atol=1e-12 * scale)
        names = ("pe", "gdot", "inertial", "S", "c", "nu")
        for q, name in enumerate(names):
            np.testing.assert_allclose(r[12 + q], ref[name][p], rtol=1e-9, atol=1e-14,
                                       err_msg=name)  # fmt: skip


def test_tensor_law_is_objective():
    """σ(Q L Qᵀ, Q ε Qᵀ) = Q σ(L, ε) Qᵀ for a rotation Q: the out-of-plane terms (xz, yz) that
    plane strain never exercises are checked against the in-plane ones."""
    cfg = _cfg()
    st = build(cfg, 3)
    k = kernels(3)
    rng = np.random.default_rng(7)
    L, e, J, phi = _random_state(rng, 16, 3)
    from scipy.spatial.transform import Rotation

    Q = Rotation.random(16, random_state=11).as_matrix()
    Lr = Q @ L @ Q.transpose(0, 2, 1)
    er = mat_to_sym(Q @ sym_to_mat(e) @ Q.transpose(0, 2, 1))
    R = _law_at(k, st.mat, L, e, J, phi, 0.0, 1e-4)
    RR = _law_at(k, st.mat, Lr, er, J, phi, 0.0, 1e-4)
    for p in range(16):
        r, rr = R[p], RR[p]
        sig = sym_to_mat(r[None, 6:12])[0]
        rot = mat_to_sym((Q[p] @ sig @ Q[p].T)[None])[0]
        np.testing.assert_allclose(rr[6:12], rot, atol=1e-9 * np.abs(sig).max())
        np.testing.assert_allclose(rr[12:], r[12:], rtol=1e-9, atol=1e-14)


def test_plane_strain_law_matches_the_2d_reference():
    """The 2-D specialisation of the tensor law is the seed's plane-strain law (materials.fei2016
    NumPy reference, components (xx, yy, xy, zz))."""
    from segmpm.materials.fei2016 import fei_update_np

    cfg = _cfg(["geometry.dimension=2"])
    st = build(cfg, 2)
    k = kernels(2)
    rng = np.random.default_rng(5)
    L, e, J, phi = _random_state(rng, 32, 2)
    L2 = L[:, :2, :2]
    eps4 = np.stack([e[:, 0], e[:, 1], e[:, 3], e[:, 2]], axis=1)
    ref = fei_update_np(st.mp, L2, 1e-4, eps4, J, phi)
    R = _law_at(k, st.mat, L, e, J, phi, 0.0, 1e-4)
    for p in range(32):
        r = R[p]
        np.testing.assert_allclose(r[[0, 1, 3, 2]], ref[0][p], rtol=1e-10, atol=1e-15)
        np.testing.assert_allclose(r[[6, 7, 9, 8]], ref[1][p], rtol=1e-10,
                                   atol=1e-12 * np.abs(ref[1][p]).max())  # fmt: skip
        np.testing.assert_allclose(r[12], ref[2][p], rtol=1e-10)
        np.testing.assert_allclose(r[13], ref[3][p], rtol=1e-10, atol=1e-14)


def test_p2g_matches_numpy_reference():
    cfg = _cfg(["geometry.depth=0.004", "geometry.width=0.003"])
    st = build(cfg, 3)
    k = kernels(3)
    P, G = st.points, st.grid
    rng = np.random.default_rng(1)
    n = st.n
    P.v[:] = rng.normal(size=P.v.shape)
    P.C[:] = rng.normal(scale=10.0, size=P.C.shape)
    P.sig[:] = rng.normal(scale=100.0, size=P.sig.shape)
    P.x[0] = (P.x[0] + rng.uniform(-2e-4, 2e-4, n)) % 0.002  # off the lattice, wrapping
    k.slab_index(P, st.prm, G.slab_start.shape[0] - 1)
    from segmpm.engine.helpers import counting_sort

    counting_sort(P.cursor, G.slab_start, G.order, 1)
    k.p2g(P, G, st.prm, False)
    prm = st.prm[0]
    m, mom, f = p2g_np(P.x.T, P.v.T, P.C.T.reshape(n, 3, 3), P.mass, P.vol0 * P.J,
                       sym_to_mat(P.sig.T), prm["h"], prm["origin"], G.nodes.shape[:3],
                       True)  # fmt: skip
    np.testing.assert_allclose(G.nodes[..., k.F_M], m, rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(G.nodes[..., k.F_P : k.F_P + 3], mom, rtol=1e-11,
                               atol=1e-12 * np.abs(mom).max())  # fmt: skip
    np.testing.assert_allclose(G.nodes[..., k.F_F : k.F_F + 3], f, rtol=1e-11,
                               atol=1e-12 * np.abs(f).max())  # fmt: skip
    # the MUSL remap scatters from P.x_old, which a run without MUSL does not allocate
    with pytest.raises(ValueError, match="x_old"):
        k.p2g(P, G, st.prm, True)


def _run(st, t_end, threads=1, chunk=500):
    import numba

    k = for_material(st.dim, st.mat)
    numba.set_num_threads(threads)
    while st.clock[0]["time"] < t_end:
        status, idx, _ = k.advance(st.points, st.grid, st.prm, st.mat, st.clock, st.seg, t_end,
                                   chunk)  # fmt: skip
        assert status == 0, (status, idx)
    return st


@pytest.mark.parametrize("transfer", ["aflip", "flip"])
def test_frictionless_walls_give_plane_strain(transfer):
    """A 3-D chute between frictionless walls is z-invariant: it is the 2-D chute without the
    sidewall force, to round-off (with the image nodes behind the walls, every node layer sees
    the mirror-extended material, whose z stencil sums to one). The same holds for the MUSL
    transfer, whose remap and gradient pass the z stencil too."""
    common = ["geometry.depth=0.006", "geometry.width=0.003", "boundary.sidewall_friction=0",
              "grid.volumetric_smoothing='off'", f"grid.transfer='{transfer}'"]  # fmt: skip
    s3 = _run(build(_cfg(common), 3), 0.03)
    s2 = _run(build(_cfg([*common, "geometry.dimension=2"]), 2), 0.03)
    P3, P2 = s3.points, s2.points
    nz = 6  # points across the width (3 mm at 0.5 mm)
    assert P3.mass.size == nz * P2.mass.size
    u_s = np.abs(P2.v[0]).max()
    assert u_s > 1e-3  # it flows
    v3 = P3.v[0].reshape(-1, nz)  # lattice order: z fastest
    np.testing.assert_allclose(v3, np.repeat(P2.v[0][:, None], nz, axis=1), atol=1e-9 * u_s)
    assert np.abs(P3.v[2]).max() < 1e-9 * u_s
    np.testing.assert_allclose(P3.sig[3].reshape(-1, nz)[:, 0], P2.sig[3],
                               atol=1e-8 * np.abs(P2.sig[1]).max())  # fmt: skip


def test_frictionless_walls_stay_z_invariant_with_volumetric_smoothing():
    """The volumetric smoothing keeps a z-invariant state z-invariant:
    the 3-D chute between frictionless walls has equal columns across the width and no v_z,
    and it still flows like plane strain (the smoothing only redistributes tr L within a few
    cells, and the state is uniform along the layer)."""
    common = ["geometry.depth=0.006", "geometry.width=0.003", "boundary.sidewall_friction=0"]
    s3 = _run(build(_cfg([*common, "grid.volumetric_smoothing='on'"]), 3), 0.03)
    s2 = _run(build(_cfg([*common, "geometry.dimension=2"]), 2), 0.03)
    assert s3.prm[0]["dilatation"] == 1 and s2.prm[0]["dilatation"] == 0
    P3, P2 = s3.points, s2.points
    nz = 6
    u3 = P3.v[0].reshape(-1, nz)
    u_s = np.abs(u3).max()
    assert u_s > 1e-3
    np.testing.assert_allclose(u3, np.repeat(u3[:, :1], nz, axis=1), atol=1e-9 * u_s)
    np.testing.assert_allclose(P3.J.reshape(-1, nz), np.repeat(P3.J.reshape(-1, nz)[:, :1], nz,
                                                               axis=1), atol=1e-13)  # fmt: skip
    assert np.abs(P3.v[2]).max() < 1e-9 * u_s
    # the same chute in plane strain without the smoothing: the velocities agree to the
    # smoothing's O(h²) change of the elastic volume strain, far below the flow
    np.testing.assert_allclose(u3[:, 0], P2.v[0], atol=2e-3 * np.abs(P2.v[0]).max())


def _smoothing_state():
    cfg = _cfg(["geometry.depth=0.010", "geometry.width=0.004", "grid.volumetric_smoothing='on'"])
    st = build(cfg, 3)
    assert st.prm[0]["dilatation"] == 1
    return st, kernels(3)


def test_volumetric_smoothing_matches_numpy_reference_and_conserves_the_volume_rate():
    """smooth_dilatation against its point-by-point NumPy reference, off the lattice with a
    random L; and Σ m tr L̄ = Σ m tr L (the nodal averages are mass-weighted and every point's
    weights sum to one), so that the smoothing moves volume change, never creates it."""
    from segmpm.engine.reference import smooth_dilatation_np

    st, k = _smoothing_state()
    P, G = st.points, st.grid
    rng = np.random.default_rng(7)
    n = st.n
    P.x[0] = (P.x[0] + rng.uniform(-2e-4, 2e-4, n)) % 0.002
    P.x[1] += rng.uniform(-2e-4, 2e-4, n)
    P.x[2] += rng.uniform(-2e-4, 2e-4, n)
    P.lg[:] = rng.normal(scale=5.0, size=P.lg.shape)
    P.J[:] = rng.uniform(0.99, 1.01, n)
    L0 = P.lg.T.reshape(n, 3, 3).copy()
    J0 = P.J.copy()
    dt = 1e-4
    k.smooth_dilatation(P, G, st.prm, dt)
    prm = st.prm[0]
    Lref, Jref = smooth_dilatation_np(P.x.T, P.mass, L0, J0, prm["h"], prm["origin"],
                                      G.nodes.shape[:3], True, dt)  # fmt: skip
    np.testing.assert_allclose(P.lg.T.reshape(n, 3, 3), Lref, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(P.J, Jref, rtol=1e-14)
    tr0 = np.trace(L0, axis1=1, axis2=2)
    tr1 = np.trace(Lref, axis1=1, axis2=2)
    assert abs((P.mass * tr1).sum() - (P.mass * tr0).sum()) < 1e-12 * (P.mass * abs(tr0)).sum()
    # the deviatoric part of L is untouched
    dev = L0 - tr0[:, None, None] / 3 * np.eye(3)
    np.testing.assert_allclose(Lref - tr1[:, None, None] / 3 * np.eye(3), dev, atol=1e-12)


def test_volumetric_smoothing_removes_the_row_mode_and_keeps_linear_fields():
    """On the lattice of 2 points per cell and axis (equal masses): a volumetric rate that
    alternates between point rows (the null mode of the B-spline force: the rows' stresses
    cancel in every nodal force) averages to zero at every node whose stencil is full, and a
    rate linear in y is reproduced exactly there (the nodal averages of a linear field are its
    nodal values by symmetry, and quadratic B-splines interpolate linear fields exactly)."""
    st, k = _smoothing_state()
    P, G = st.points, st.grid
    h = st.prm[0]["h"]
    y = P.x[1]
    interior = (y > 3 * h) & (y < 0.010 - 3 * h)  # every stencil node has both rows around
    row = np.rint((y / (h / 2)) - 0.5).astype(int)
    P.mass[:] = P.mass.mean()  # the geostatic state's masses vary with depth (by < 1e-3)
    P.lg[:] = 0.0
    P.lg[0] = 1e-2 * (-1.0) ** row
    k.smooth_dilatation(P, G, st.prm, 0.0)
    tr = P.lg[0] + P.lg[4] + P.lg[8]
    assert np.abs(tr[interior]).max() < 1e-15
    assert np.abs(tr[~interior]).max() > 1e-4  # near the base and the surface it does not cancel
    P.lg[:] = 0.0
    P.lg[4] = 3.0 - 200.0 * y  # tr L = 3 − 200 y, 1/s
    k.smooth_dilatation(P, G, st.prm, 0.0)
    tr = P.lg[0] + P.lg[4] + P.lg[8]
    np.testing.assert_allclose(tr[interior], 3.0 - 200.0 * y[interior], rtol=0, atol=1e-13)


@pytest.mark.parametrize("n_y, null", [(2, True), (3, False)])
def test_row_stress_is_a_null_mode_at_2_points_per_cell_only(n_y, null):
    """A normal stress σ_yy = ±s alternating from one point row to the next (in y) exerts no
    force on any node whose stencil is full at 2 points per cell along y: the quadratic
    B-spline's w′ at the rows ±¼, ±¾, ±5⁄4 h from a node gives −½ + ¾ − ¼ = 0 in alternating
    sum. At 3 per cell (rows ±⅙, ±½, ±⅚, ±7⁄6 h) the same sum is 2(−⅓ + 1 − ⅔ + ⅓) = ⅔, so each
    interior node feels |f_y| = ⅔ s V n_x n_z / h: the grid resists the mode (docs/model.md §2,
    "Points per cell per axis")."""
    from segmpm.engine.helpers import counting_sort

    cfg = _cfg(["geometry.depth=0.010", "geometry.width=0.004",
                f"grid.particles_per_cell=[2, {n_y}, 2]"])  # fmt: skip
    st, k = build(cfg, 3), kernels(3)
    P, G, prm = st.points, st.grid, st.prm[0]
    h, s = prm["h"], 100.0
    P.v[:] = 0.0
    P.C[:] = 0.0
    P.J[:] = 1.0
    P.vol0[:] = P.vol0.mean()  # one volume V (the geostatic J varies it by < 1e-3)
    row = np.rint(P.x[1] / (h / n_y) - 0.5).astype(int)

    def force():
        k.slab_index(P, st.prm, G.slab_start.shape[0] - 1)
        counting_sort(P.cursor, G.slab_start, G.order, 1)
        k.p2g(P, G, st.prm, False)
        return G.nodes[..., k.F_F + 1].copy()

    P.sig[:] = 0.0
    f0 = force()
    P.sig[1] = s * (-1.0) ** row
    fy = force() - f0
    # nodes whose stencils lie inside the layer in y and z (2 cells from the base, the surface
    # and the open sides of the box); x is periodic
    y = prm["origin"][1] + h * np.arange(G.nodes.shape[1])
    z = prm["origin"][2] + h * np.arange(G.nodes.shape[2])
    iy = (y >= 2 * h) & (y <= 0.010 - 2 * h)
    iz = (z >= 2 * h) & (z <= 0.004 - 2 * h)
    inner = np.abs(fy[:, iy][:, :, iz])
    scale = 2.0 / 3.0 * s * P.vol0[0] * 2 * 2 / h
    if null:
        assert inner.max() < 1e-12 * scale
    else:
        np.testing.assert_allclose(inner, scale, rtol=1e-9)


def test_volumetric_smoothing_on_in_2d_names_the_key_and_auto_is_nonlocal_3d_only():
    with pytest.raises(ConfigError, match="grid.volumetric_smoothing"):
        _cfg(["geometry.dimension=2", "grid.volumetric_smoothing='on'"])
    small = ["geometry.depth=0.004", "geometry.width=0.002"]
    assert build(_cfg(small), 3).prm[0]["dilatation"] == 0  # local rheology
    assert build(_nl_cfg(small), 3).prm[0]["dilatation"] == 1
    assert build(_nl_cfg(small, dim=2), 2).prm[0]["dilatation"] == 0


def test_resolved_wall_coulomb_friction_sliding_block():
    """A block pressed onto the wall z = 0 by gravity and pulled along x slides with
    a = g (sin θ − μ cos θ) (Coulomb friction of the resolved wall)."""
    mu, theta, g = 0.3, np.radians(40.0), 9.81
    cfg = _cfg(["material.model='linear_elastic'", "material.youngs_modulus=2e5",
                "material.poisson_ratio=0.3", "geometry.depth=0.004", "geometry.width=0.004",
                f"boundary.sidewall_friction={mu}", "material.initial_state='stress_free'",
                "time.cfl=0.3"])  # fmt: skip
    st = build(cfg, 3)
    prm = st.prm
    prm["base_kind"] = PLANE_CODES["open"]
    prm["zhi_kind"] = PLANE_CODES["open"]
    prm["gravity"][0] = (g * np.sin(theta), 0.0, -g * np.cos(theta))
    P = st.points  # no gravity along y, no base: the block is only pressed onto z = 0
    _run(st, 0.02)
    v0 = float(np.average(P.v[0], weights=P.mass))
    t0 = st.clock[0]["time"]
    _run(st, 0.06)
    v1 = float(np.average(P.v[0], weights=P.mass))
    a = (v1 - v0) / (st.clock[0]["time"] - t0)
    expected = g * (np.sin(theta) - mu * np.cos(theta))
    assert a == pytest.approx(expected, rel=0.03)


def test_3d_result_does_not_depend_on_threads():
    common = ["geometry.depth=0.008", "geometry.width=0.004"]
    a = _run(build(_cfg(common), 3, threads=1), 0.02, threads=1)
    b = _run(build(_cfg(common), 3, threads=2), 0.02, threads=2)
    for name in ("x", "v", "sig", "J"):
        np.testing.assert_array_equal(getattr(a.points, name), getattr(b.points, name))


def test_thread_count_set_after_set_up_is_used_and_changes_nothing():
    """``sim.threads`` set after set-up (the bench does it; "auto" gives one thread to a small
    case) resizes P2G's per-thread slab runs to the new count, so that P2G runs on every
    thread, and the result is the same bitwise."""
    from segmpm.simulation import Simulation

    cfg = ["geometry.depth=0.008", "grid.engine='generic'", "grid.threads='auto'"]
    a, b = Simulation(_seed2d(cfg)), Simulation(_seed2d(cfg))
    assert a.engine.grid.bounds.shape[0] == 2  # auto: a small case is serial
    b.threads = 2
    for s in (a, b):
        status, _, steps = s.advance(1.0, 200)
        assert (status, steps) == (0, 200)
    assert b.engine.grid.bounds.shape[0] == 3
    for name in ("x", "v", "sig", "J"):
        np.testing.assert_array_equal(getattr(a.engine.points, name),
                                      getattr(b.engine.points, name))  # fmt: skip


def test_3d_run_resumes_to_the_same_result(tmp_path):
    """The default (nonlocal, grain-calibrated) model in 3-D: an interrupted run resumes to the
    same state, fluidity and fluidity clock included."""
    from segmpm.simulation import Simulation

    common = ["geometry.depth=0.006", "geometry.width=0.004", "geometry.mirror=true",
              "output.checkpoint_interval=0.01", "output.profile_times=[0.0, 0.01, 0.02]"]  # fmt: skip
    full = Simulation(_nl_cfg([*common, "time.end=0.02"]), tmp_path / "full")
    assert full.dim == 3
    assert full.run().status == "completed"
    part = Simulation(_nl_cfg([*common, "time.end=0.01"]), tmp_path / "part")
    assert part.run().status == "completed"
    cont = Simulation(_nl_cfg([*common, "time.end=0.02"]), tmp_path / "part")
    assert cont.run(resume=True).status == "completed"
    np.testing.assert_array_equal(full.engine.points.v, cont.engine.points.v)
    np.testing.assert_array_equal(full.engine.points.gf, cont.engine.points.gf)
    assert full.engine.points.gf.max() > 0.0
    assert full.engine.clock[0]["nflu"] == cont.engine.clock[0]["nflu"] > 0
    import json

    info = json.loads((tmp_path / "part" / "run.json").read_text())
    assert info["fluidity_updates"] == int(full.engine.clock[0]["nflu"])
    import xarray as xr

    with (
        xr.open_dataset(tmp_path / "full" / "cross_section.nc") as a,
        xr.open_dataset(tmp_path / "part" / "cross_section.nc") as b,
    ):
        assert list(a.time.values) == list(b.time.values) == [0.0, 0.01, 0.02]
        np.testing.assert_array_equal(a.velocity_x.values, b.velocity_x.values)
        assert a.velocity_x.shape == (3, a.y.size, 2)  # 2 mm modelled, 1 mm cells


@pytest.mark.parametrize(
    "override, key",
    [
        ("geometry.width=0.0215", "geometry.width"),
        ("scenario.solver='column'", "scenario.solver"),
    ],
)
def test_3d_unsupported_input_names_the_key(override, key):
    with pytest.raises(ConfigError, match=key.replace(".", r"\.")):
        load_config(None, [*LOCAL3D, *override.split(", ")], preset="chute_seed")


def test_a_point_leaving_the_grid_stops_the_loop():
    """A point thrown out of the top of the grid is flagged by G2P and stops the loop with
    ST_LEFT_GRID before the next P2G (which would write outside the grid)."""
    from segmpm.mpm.params import ST_LEFT_GRID

    st = build(_cfg(["geometry.depth=0.006", "geometry.width=0.004"]), 3)
    P = st.points
    top = int(np.argmax(P.x[1]))
    P.v[1, top] = 50.0  # one cell per ~20 µs: out of the 1.8 mm headroom within a few steps
    k = for_material(3, st.mat)
    status, idx, steps = k.advance(P, st.grid, st.prm, st.mat, st.clock, st.seg, 1.0, 10_000)
    assert (status, idx) == (ST_LEFT_GRID, top)
    assert steps < 10_000
    assert np.all(P.cursor >= 0)  # G2P wrote every point's slab


def _seg_state(dim, rng, extra=()):
    cfg = _cfg(["segregation.model='hill_tan_reduced'", "geometry.depth=0.006",
                "geometry.width=0.003", "boundary.sidewall_friction=0", *extra])  # fmt: skip
    if dim == 2:
        cfg = _cfg(["segregation.model='hill_tan_reduced'", "geometry.depth=0.006",
                    "geometry.dimension=2", *extra])  # fmt: skip
    st = build(cfg, dim)
    return cfg, st


def test_concentration_step_3d_conserves_and_reduces_to_2d():
    """3-D: Σ V⁰ φ_s is conserved to round-off, 0 ≤ φ_s ≤ 1, and a z-uniform state gives the 2-D
    result on every z layer (no flux through the z-faces)."""
    rng = np.random.default_rng(4)
    _, s3 = _seg_state(3, rng)
    _, s2 = _seg_state(2, rng)
    nz = 6
    P3, P2 = s3.points, s2.points
    phi = rng.uniform(0.0, 1.0, P2.mass.size)
    drv = 1e-3 * (40.0 - 5e3 * P2.x[1])
    P2.phi[:] = phi
    P2.s_int[:] = drv
    P2.g_int[:] = 2e-2
    P3.phi[:] = np.repeat(phi, nz)
    P3.s_int[:] = np.repeat(drv, nz)
    P3.g_int[:] = 2e-2
    total = float(np.sum(P3.vol0 * P3.phi))
    kernels(3).concentration_step(P3, s3.seg, 1e-3)
    kernels(2).concentration_step(P2, s2.seg, 1e-3)
    assert float(np.sum(P3.vol0 * P3.phi)) == pytest.approx(total, rel=1e-13)
    assert P3.phi.min() >= 0.0 and P3.phi.max() <= 1.0
    np.testing.assert_allclose(P3.phi.reshape(-1, nz), np.repeat(P2.phi[:, None], nz, axis=1),
                               atol=1e-12)  # fmt: skip


def test_3d_collapse_quarter_column_is_symmetric():
    """The quarter cylinder (symmetry planes x = 0 and z = 0) spreads alike along x and z (the
    problem is symmetric under x ↔ z), keeps its mass, and does not cross the symmetry planes."""
    cfg = _cfg(["scenario.kind='collapse'", "geometry.slope_deg=0", "geometry.length=0.012",
                "geometry.column_width=0.005", "geometry.column_height=0.005",
                "boundary.base='noslip'"])  # fmt: skip
    st = _run(build(cfg, 3), 0.04)
    P = st.points
    px = float(np.sum(P.mass * P.v[0]))
    pz = float(np.sum(P.mass * P.v[2]))
    assert px > 1e-8  # it spreads outwards
    assert pz == pytest.approx(px, rel=1e-6)
    rx = float(np.sum(P.mass * P.x[0]))
    rz = float(np.sum(P.mass * P.x[2]))
    assert rz == pytest.approx(rx, rel=1e-8)
    assert P.x[0].min() > 0.0 and P.x[2].min() > 0.0


@pytest.mark.parametrize("dim", [2, 3])
def test_solid_fraction_profile_does_not_depend_on_the_lattice(dim):
    """The depth profile of the solid fraction f (and its cross-section map in 3-D) is a property
    of the material, not of the points: a lattice of 3 points per 1 mm cell along y, whose
    spacing does not divide the 0.5 mm bins, gives the f of 2 per cell, whose spacing does, in
    every bin, and both hold the points' whole solid volume. (Binning each point at its centre
    gave 0.8, 0.4, 0.8, ... at 3 per cell.) The tolerance is the geostatic strain of the initial
    state, f/f_0 − 1 ≤ 1e-3 here: a slab of the reference spacing Δ = h/3 misplaces at most that
    fraction of a point's volume."""
    from conftest import make_sim

    base = ["material.rheology='local'", "segregation.model='none'", f"geometry.dimension={dim}",
            "grid.cell_size=0.001", "geometry.length=0.002", "geometry.depth=0.006"]  # fmt: skip
    if dim == 3:
        base += ["geometry.width=0.004", "geometry.mirror=true"]
    out = {}
    for ny in (2, 3):
        sim = make_sim([*base, f"grid.particles_per_cell={[2] + [ny] * (dim - 1)}"])
        P = sim.engine.points
        f = sim.profiles()["solid_fraction"]
        solid = float(np.sum(P.mass)) / sim.config.material.grain_density
        width = float(sim.edges[1] - sim.edges[0])
        assert np.nansum(f) * sim._area() * width == pytest.approx(solid, rel=1e-12)
        out[ny] = (f, sim.cross_section()[2]["solid_fraction"] if dim == 3 else None)
    (f2, c2), (f3, c3) = out[2], out[3]
    filled = ~np.isnan(f2)
    assert filled.sum() == 12 and np.array_equal(filled, ~np.isnan(f3))  # 6 mm in 0.5 mm bins
    assert abs(np.nanmax(f2) / 0.6 - 1) < 1e-3  # the geostatic strain bounds the tolerance
    np.testing.assert_allclose(f3[filled], f2[filled], rtol=1e-3, atol=0)
    if dim == 3:
        np.testing.assert_allclose(c3[filled], c2[filled], rtol=1e-3, atol=0)


def test_3d_cli_run_writes_3d_snapshots_and_cross_sections(tmp_path):
    import json
    import subprocess
    import sys

    import meshio
    import xarray as xr

    out = tmp_path / "run3d"
    args = [sys.executable, "-m", "segmpm.cli", "run", "chute_seed", "--out", str(out),
            "--no-progress", "--set", "output.profile_times=[0.0, 0.005]", "--set",
            "time.end=0.005", "--set", "geometry.depth=0.006", "--set", "geometry.width=0.004",
            "--set", "geometry.mirror=true"]  # fmt: skip
    for o in LOCAL3D:
        if not o.startswith("output."):
            args += ["--set", o]
    r = subprocess.run(args, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr
    info = json.loads((out / "run.json").read_text())
    assert info["status"] == "completed" and info["dimension"] == 3
    mesh = meshio.read(out / "fields" / "particles_0001.vtu")
    assert mesh.points.shape[0] == info["n_points"]
    assert mesh.points[:, 2].max() > 1e-3  # the z coordinates are written
    assert "velocity_z" in mesh.point_data
    with xr.open_dataset(out / "cross_section.nc") as ds:
        assert ds.velocity_x.dims == ("time", "y", "z") and ds.z.size == 2
    with xr.open_dataset(out / "profiles.nc") as ds:
        f = ds.solid_fraction.sel(time=0.0).values
        assert np.nanmedian(f) == pytest.approx(0.6, rel=0.02)  # area = length × modelled width


# ---------------------------------------------------------------------------------------------
# the nonlocal rheology on the generic engine


def _nl_cfg(extra=(), dim=3):
    """The grain-calibrated nonlocal preset on a small 3-D (or 2-D) strip."""
    return load_config(None, [*LOCAL3D[1:], "material.rheology='nonlocal'",
                              f"geometry.dimension={dim}", *extra],
                       preset="chute_nonlocal")  # fmt: skip


@pytest.mark.parametrize("driver", ["P", "G", "A"])
def test_nonlocal_tensor_law_matches_numpy_reference(driver):
    """The fluidity flow rule in full tensor form against the full-matrix NumPy reference (its
    return factor by bisection), for fluidities from none to far past the return's stiff
    limit G Δt g ≫ p."""
    cfg = _nl_cfg([f"segregation.driver='{driver}'", "segregation.model='none'"])
    st = build(cfg, 3)
    k = kernels(3)
    rng = np.random.default_rng(13)
    n = 64
    L, e, J, phi = _random_state(rng, n, 3)
    J[:4] = np.exp(1e-3)  # gas
    g = 10.0 ** rng.uniform(-3, 4, n)
    g[4:8] = 0.0
    dt = 1e-4
    ref = ngf_tensor_np(st.mat[0], L, e, J, phi, g, dt)
    R = _law_at(k, st.mat, L, e, J, phi, g, dt)
    for p in range(n):
        r = R[p]
        np.testing.assert_allclose(r[0:6], ref["eps"][p], rtol=1e-9, atol=1e-15)
        scale = max(1.0, np.abs(ref["sig"][p]).max())
        np.testing.assert_allclose(r[6:12], ref["sig"][p], rtol=1e-9, atol=1e-11 * scale)
        for q, name in enumerate(("pe", "gdot", "inertial", "S", "c", "nu")):
            np.testing.assert_allclose(r[12 + q], ref[name][p], rtol=1e-9, atol=1e-14,
                                       err_msg=name)  # fmt: skip


def test_nonlocal_tensor_law_is_objective_and_plane_strain_is_the_2d_law():
    """σ(Q L Qᵀ, Q ε Qᵀ) = Q σ Qᵀ for rotations Q; the 2-D specialisation is the
    plane-strain law (materials.ngf NumPy reference, components (xx, yy, xy, zz))."""
    from scipy.spatial.transform import Rotation

    from segmpm.materials.ngf import ngf_update_np

    st = build(_nl_cfg(["segregation.model='none'"]), 3)
    k = kernels(3)
    rng = np.random.default_rng(17)
    L, e, J, phi = _random_state(rng, 16, 3)
    g = 10.0 ** rng.uniform(-2, 3, 16)
    Q = Rotation.random(16, random_state=5).as_matrix()
    Lr = Q @ L @ Q.transpose(0, 2, 1)
    er = mat_to_sym(Q @ sym_to_mat(e) @ Q.transpose(0, 2, 1))
    R = _law_at(k, st.mat, L, e, J, phi, g, 1e-4)
    RR = _law_at(k, st.mat, Lr, er, J, phi, g, 1e-4)
    for p in range(16):
        r, rr = R[p], RR[p]
        sig = sym_to_mat(r[None, 6:12])[0]
        np.testing.assert_allclose(rr[6:12], mat_to_sym((Q[p] @ sig @ Q[p].T)[None])[0],
                                   atol=1e-9 * np.abs(sig).max())  # fmt: skip
        np.testing.assert_allclose(rr[12:], r[12:], rtol=1e-9, atol=1e-14)

    st2 = build(_nl_cfg(["segregation.model='none'"], dim=2), 2)
    k2 = kernels(2)
    L, e, J, phi = _random_state(rng, 32, 2)
    g = 10.0 ** rng.uniform(-2, 3, 32)
    eps4 = np.stack([e[:, 0], e[:, 1], e[:, 3], e[:, 2]], axis=1)
    ref = ngf_update_np(st2.mp, L[:, :2, :2], 1e-4, eps4, J, phi, g)
    R = _law_at(k2, st2.mat, L, e, J, phi, g, 1e-4)
    for p in range(32):
        r = R[p]
        np.testing.assert_allclose(r[[0, 1, 3, 2]], ref[0][p], rtol=1e-9, atol=1e-15)
        np.testing.assert_allclose(r[[6, 7, 9, 8]], ref[1][p], rtol=1e-9,
                                   atol=1e-11 * np.abs(ref[1][p]).max())  # fmt: skip
        np.testing.assert_allclose(r[12], ref[2][p], rtol=1e-9)


def _fluidity_grid(shape, h, periodic):
    from segmpm.engine.records import PARAMS

    prm = np.zeros(1, dtype=PARAMS)
    prm["h"] = h
    prm["nodes"][:] = shape
    prm["periodic_x"] = 1 if periodic else 0
    return prm


def test_fluidity_diffusion_decays_the_discrete_eigenmodes_exactly():
    """The 3-D fluidity diffusion (explicit finite volumes, sub-stepped) on a box of active
    nodes: periodic in x, zero-flux (free surface / frictional wall) ends in z, Dirichlet nodes
    (a rough wall, g = 0) at both ends in y. A product of the discrete eigenmodes
    cos(2π i/N_x) sin(π j/(N_y − 1)) cos(π (k + ½)/N_z) decays by (1 − Δs D λ)^n_sub with
    λ = Σ_axes (2 − 2 cos θ_axis)/h² — the closed form of the scheme, to round-off."""
    k3 = kernels(3)
    nx, ny, nz, h, D0 = 8, 9, 6, 1e-3, 2e-3
    prm = _fluidity_grid((nx, ny, nz), h, True)
    fw = np.zeros((k3.NW, nx, ny, nz))
    i, j, kk = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    mode = (np.cos(2 * np.pi * i / nx) * np.sin(np.pi * j / (ny - 1))
            * np.cos(np.pi * (kk + 0.5) / nz))  # fmt: skip
    fw[k3.W_KIND] = k3.K_ACTIVE
    fw[k3.W_KIND][:, [0, ny - 1], :] = k3.K_DIRICHLET
    fw[k3.W_CAP] = 1.0
    fw[k3.W_DIFF] = D0
    fw[k3.W_G] = np.where(fw[k3.W_KIND] == k3.K_ACTIVE, mode, 0.0)
    dt = 2e-4
    nsub = k3.diffuse(fw, prm, dt, D0, np.zeros((0, 3), dtype=np.int64))
    lam = ((2 - 2 * np.cos(2 * np.pi / nx)) + (2 - 2 * np.cos(np.pi / (ny - 1)))
           + (2 - 2 * np.cos(np.pi / nz))) / h**2  # fmt: skip
    assert nsub == int(np.ceil(dt * 6 * D0 / h**2 / 0.9))
    expected = mode * (1 - dt / nsub * D0 * lam) ** nsub
    active = fw[k3.W_KIND] == k3.K_ACTIVE
    np.testing.assert_allclose(fw[k3.W_G][active], expected[active], rtol=0, atol=1e-13)
    # and the continuous decay, to the scheme's O(h²) + O(Δs) error
    lam_c = ((2 * np.pi / (nx * h)) ** 2 + (np.pi / ((ny - 1) * h)) ** 2
             + (np.pi / (nz * h)) ** 2)  # fmt: skip
    ratio = np.abs(fw[k3.W_G][active]).max() / np.abs(mode[active]).max()
    assert ratio == pytest.approx(np.exp(-D0 * lam_c * dt), rel=0.05)


def test_fluidity_step_2d_is_the_numpy_twin():
    """The engine's fluidity update in 2-D (P2G, node kinds, cut-cell diffusion, G2P with the PIC
    share, local relaxation) is the NumPy twin mpm.fluidity.fluidity_step_np on the same points
    (the twin's grid record from the 2-D reference builder), to round-off."""
    from segmpm.mpm.fluidity import fluidity_step_np
    from segmpm.mpm.params import G_H, G_NX, G_NY, G_X0, G_Y0
    from segmpm.scenarios import build as twin_build

    over = ["geometry.depth=0.008", "segregation.model='none'"]
    cfg = _nl_cfg(over, dim=2)
    st = build(cfg, 2)
    P = st.points
    rng = np.random.default_rng(23)
    n = st.n
    P.phi[:] = rng.uniform(0.2, 0.8, n)
    P.gf[:] = np.where(rng.random(n) < 0.2, 0.0, 10.0 ** rng.uniform(-1, 2, n))
    tau = rng.uniform(0.2, 0.6, n) * P.diag[0]  # a shear stress: μ around μ_s
    P.sig[3] = tau
    gp = twin_build(cfg).gp
    pr = st.prm[0]
    assert (gp[G_X0], gp[G_Y0], gp[G_H]) == (pr["origin"][0], pr["origin"][1], pr["h"])
    assert (int(gp[G_NX]), int(gp[G_NY])) == tuple(pr["nodes"][:2])
    sig4 = np.stack([P.sig[0], P.sig[1], P.sig[3], P.sig[2]])
    dt = 2.5e-4
    gref, nref = fluidity_step_np(P.x, P.mass, P.phi, sig4, P.diag[0], P.gf.copy(), gp, st.mp, dt)
    g0 = P.gf.copy()
    nsub = kernels(2).fluidity_step(P, st.grid, st.prm, st.mat, dt)
    assert nsub == nref > 0
    np.testing.assert_allclose(P.gf, gref, rtol=1e-10, atol=1e-300)
    assert np.abs(P.gf - g0).max() > 0.05 * np.abs(g0).max()  # something happened


def test_nonlocal_chute_between_frictionless_walls_is_plane_strain():
    """A 3-D nonlocal chute between frictionless walls is the 2-D nonlocal chute without the
    sidewall force, to round-off: the fluidity's P2G, diffusion (zero flux through the walls by
    the even extension) and G2P are z-invariant for a z-invariant state. The fluidity update runs
    every step of Δt = 10 µs, so that its diffusion takes one sub-step in both dimensions (the
    explicit limit h²/(2 D D_max) allows fewer in 2-D)."""
    common = ["geometry.depth=0.006", "geometry.width=0.003", "boundary.sidewall_friction=0",
              "boundary.sidewall_slip_speed=0", "segregation.model='none'",
              "material.fluidity_dt=1e-5", "time.dt_max=1e-5",
              "grid.volumetric_smoothing='off'"]  # fmt: skip
    t_end = 0.040125  # half-way between two fluidity updates (every 2.5e-4 s): no tie
    s3 = _run(build(_nl_cfg(common), 3), t_end)
    s2 = _run(build(_nl_cfg(common, dim=2), 2), t_end)
    P3, P2 = s3.points, s2.points
    nz = 6
    assert s3.clock[0]["nflu"] == s2.clock[0]["nflu"] >= s2.clock[0]["step"] - 1
    u_s = np.abs(P2.v[0]).max()
    assert u_s > 1e-4 and P2.gf.max() > 0.0  # it flows
    np.testing.assert_allclose(P3.v[0].reshape(-1, nz), np.repeat(P2.v[0][:, None], nz, axis=1),
                               atol=1e-9 * u_s)  # fmt: skip
    np.testing.assert_allclose(P3.gf.reshape(-1, nz), np.repeat(P2.gf[:, None], nz, axis=1),
                               rtol=1e-8, atol=1e-9 * P2.gf.max())  # fmt: skip
    assert np.abs(P3.v[2]).max() < 1e-9 * u_s


def test_resolved_wall_speed_dependent_friction_terminal_speed():
    """A block pressed onto the wall z = 0 with the wall law μ(u) = μ₀ + (μ∞ − μ₀) u/(u + u_w)
    reaches the terminal speed where μ(u*) = tan θ: u* = u_w (tan θ − μ₀)/(μ∞ − tan θ)."""
    mu0, mu_inf, uw, theta, g = 0.1, 0.6, 0.05, np.radians(20.0), 9.81
    cfg = _cfg(["material.model='linear_elastic'", "material.youngs_modulus=2e5",
                "material.poisson_ratio=0.3", "geometry.depth=0.004", "geometry.width=0.004",
                f"boundary.sidewall_friction={mu_inf}", f"boundary.sidewall_friction_slow={mu0}",
                f"boundary.sidewall_slip_speed={uw}", "material.initial_state='stress_free'",
                "time.cfl=0.3"])  # fmt: skip
    st = build(cfg, 3)
    prm = st.prm
    prm["base_kind"] = PLANE_CODES["open"]
    prm["zhi_kind"] = PLANE_CODES["open"]
    prm["gravity"][0] = (g * np.sin(theta), 0.0, -g * np.cos(theta))
    _run(st, 0.4)
    u = float(np.average(st.points.v[0], weights=st.points.mass))
    tan = np.tan(theta)
    assert u == pytest.approx(uw * (tan - mu0) / (mu_inf - tan), rel=0.03)


# ------------------------------------------------------------------ one engine: 2-D on the generic


def _seed2d(extra=()):
    quiet = ["output.fields=false", "output.figures=false", "output.progress=false"]
    return load_config(None, [*quiet, *extra], preset="chute_seed")


def test_generic_engine_in_2d_names_what_it_lacks():
    assert (
        _seed2d(["grid.engine='generic'", "scenario.solver='column'"]).scenario.solver == "column"
    )
    with pytest.raises(ConfigError, match="scenario.solver"):  # the column is a 2-D layer
        _seed2d(["grid.engine='generic'", "scenario.solver='column'", "geometry.dimension=3",
                 "geometry.width=0.004", "geometry.mirror=true"])  # fmt: skip
    with pytest.raises(ConfigError, match="grid.volumetric_smoothing"):
        _seed2d(["grid.engine='generic'", "grid.volumetric_smoothing='on'"])
    with pytest.raises(ConfigError, match="grid.engine"):
        _seed2d(["grid.engine='fast'"])
    with pytest.raises(ConfigError, match="was removed"):  # the former plane-strain engine
        _seed2d(["grid.engine='production'"])
    assert _seed2d(["grid.engine='generic'"]).grid.engine == "generic"


def _points(rng, n, dim):
    """Random points for the material pass: compressed states with gas points among them."""
    from segmpm.engine.records import Points

    L, e, J, phi = _random_state(rng, n, dim)
    J[::17] = np.exp(rng.uniform(1e-4, 1e-3, J[::17].shape))  # gas (I₁ < 0)
    ne = 6 if dim == 3 else 4
    lg = L[:, :dim, :dim].reshape(n, dim * dim).T.copy()
    eps = e[:, [0, 1, 2, 3, 4, 5][:ne]].T.copy()
    return Points(
        x=rng.uniform(0, 0.01, (dim, n)), v=rng.normal(scale=0.3, size=(dim, n)),
        C=np.zeros((dim * dim, n)), mass=np.ones(n), vol0=np.ones(n), J=J, eps=eps,
        sig=np.zeros((ne, n)), phi=phi, gf=rng.uniform(0, 2e3, n),
        diag=np.full((6, n), -7.0), s_int=rng.uniform(0, 1e-3, n),
        g_int=rng.uniform(0, 1e-3, n), lg=lg, flags=np.zeros(n, dtype=np.int8),
        cursor=np.zeros(n, dtype=np.int32), x_old=np.zeros((dim, 0)),
    )  # fmt: skip


LAWS = {
    "fei-b1": lambda dim: _cfg([f"geometry.dimension={dim}"]),
    "fei-b0.7": lambda dim: _cfg([f"geometry.dimension={dim}", "material.b=0.7"]),
    "nonlocal": lambda dim: _nl_cfg(dim=dim),
}


@pytest.mark.parametrize("dim", [2, 3])
@pytest.mark.parametrize("law", list(LAWS))
def test_material_pass_is_the_point_law_at_every_point(dim, law):
    """``update_stress`` (blocks of points, the law a compile-time constant, a scalar reduction
    per block) gives at every point what the NumPy reference of the law gives: state, stress,
    p_e, the subcycle integrals, the maxima of c + |v| and ν; with a partial last block, gas
    points, the diagnostics written only when asked, and the first failing point."""
    from segmpm.mpm.params import ST_LEFT_GRID, ST_OK

    mat = build(LAWS[law](dim), dim).mat
    k = for_material(dim, mat)
    rng = np.random.default_rng(11)
    n = 3 * k.BLOCK + 37
    P = _points(rng, n, dim)
    before = {f: getattr(P, f).copy() for f in ("eps", "s_int", "g_int")}
    dt = 1e-5
    status, bad, smax, numax = k.update_stress(P, mat, dt, False, 2)
    assert (status, bad) == (ST_OK, -1)
    ne = k.NE
    L = np.zeros((n, 3, 3))
    L[:, :dim, :dim] = P.lg.T.reshape(n, dim, dim)
    e = np.zeros((n, 6))
    e[:, :ne] = before["eps"].T
    if law == "nonlocal":
        ref = ngf_tensor_np(mat[0], L, e, P.J, P.phi, P.gf, dt)
    else:
        ref = fei_tensor_np(mat[0], L, e, P.J, P.phi, dt)
    names = ("pe", "gdot", "inertial", "S", "c", "nu")
    r = np.column_stack([ref["eps"], ref["sig"], *(ref[q] for q in names)])
    # the pass contracts a·b + c into FMAs and the NumPy reference does not, and the reference
    # finds the nonlocal return factor by bisection (to ~1e-12 relative): round-off relative to
    # each quantity's scale (the deviatoric parts cancel to ~1e-3 of it)
    tol = 1e-9 if law == "nonlocal" else 1e-11

    def close(a, b, what):
        np.testing.assert_allclose(a, b, rtol=0, atol=tol * np.abs(b).max(), err_msg=what)

    close(P.eps, r[:, :ne].T, "eps")
    close(P.sig, r[:, 6 : 6 + ne].T, "sig")
    close(P.diag[0], r[:, 12], "p_e")
    close(P.s_int - before["s_int"], r[:, 15] * dt, "S dt")
    close(P.g_int - before["g_int"], r[:, 13] * dt, "gdot dt")
    speed = r[:, 16] + np.sqrt((P.v**2).sum(axis=0))
    assert smax == pytest.approx(speed.max(), rel=1e-12)
    assert numax == pytest.approx(r[:, 17].max(), rel=1e-12)
    assert (r[::17, 6:12] == 0.0).all() and (r[::17, 13] > 0.0).any()  # gas: no stress
    assert (P.diag[1:] == -7.0).all()  # not asked: not written
    # the first failing point in index order, its diagnostics written, the others' not
    P.eps[:] = before["eps"]
    P.flags[[n - 5, k.BLOCK + 3]] = ST_LEFT_GRID
    status, bad, _, _ = k.update_stress(P, mat, dt, False, 2)
    assert (status, bad) == (ST_LEFT_GRID, k.BLOCK + 3)
    assert (P.diag[1:, [k.BLOCK + 3, n - 5]] != -7.0).all()
    assert (np.delete(P.diag[1:], [k.BLOCK + 3, n - 5], axis=1) == -7.0).all()
    P.eps[:] = before["eps"]
    P.flags[:] = ST_OK
    k.update_stress(P, mat, dt, True, 1)  # asked: written everywhere, as in the reference
    close(P.diag[1], r[:, 13], "gdot")
    close(P.diag[4], speed, "c + |v|")


# ------------------------------------------------------- the verification bodies on the generic

BAR_E, BAR_RHO, BAR_L, BAR_V0 = 100.0, 1.0, 1.0, 0.01
BAR_PERIOD = 4 * BAR_L / math.sqrt(BAR_E / BAR_RHO)  # ω₁ = (π/2L) √(E/ρ), ν = 0


def _bar(cells, extra=()):
    h = BAR_L / cells
    return _seed2d([
        "scenario.kind='bar'", "material.model='linear_elastic'",
        f"material.youngs_modulus={BAR_E}", "material.poisson_ratio=0.0",
        "material.solid_fraction=1.0", f"material.grain_density={BAR_RHO}",
        f"geometry.length={BAR_L}", f"geometry.depth={h}", f"geometry.width={h}",
        f"grid.cell_size={h}", "geometry.headroom=0.2", f"scenario.velocity={BAR_V0}",
        "time.cfl=0.2", "grid.transfer='apic'", "segregation.model='none'", *extra,
    ])  # fmt: skip


def _bar_period(sim, periods, samples=100):
    """The period of the centre-of-mass velocity's zero crossings, and its amplitude."""
    P = sim.engine.points
    ts, vcm = [], []
    for k in range(int(periods * samples) + 1):
        sim.advance_to(k * BAR_PERIOD / samples)
        ts.append(sim.time)
        vcm.append(np.sum(P.mass * P.v[0]) / P.mass.sum())
    ts, v = np.array(ts), np.array(vcm)
    return _zero_crossing_period(ts, v), np.abs(v).max()


def _zero_crossing_period(ts, v):
    """Twice the mean spacing of the linearly interpolated sign changes of v(t)."""
    i = np.nonzero(np.sign(v[1:]) * np.sign(v[:-1]) < 0)[0]
    zc = ts[i] - v[i] * (ts[i + 1] - ts[i]) / (v[i + 1] - v[i])
    return 2 * np.mean(np.diff(zc))


def test_3d_bar_period_converges_to_the_closed_form():
    """The 3-D clamped bar (ν = 0, so its first mode is the 1-D one: T = 4L/√(E/ρ)) converges
    to the closed-form period at second order in h, as the 2-D bar does
    (tests/test_mpm_verification.py): the error falls by 4 per halving of h, within the same
    bounds on the order (1.7–2.3), and the centre of mass swings with the mode's 2v₀/π."""
    from segmpm.simulation import Simulation

    errs = {}
    for cells in (8, 16, 32):
        sim = Simulation(_bar(cells, ["geometry.dimension=3"]))
        assert sim.dim == 3
        period, amp = _bar_period(sim, 2)
        errs[cells] = abs(period - BAR_PERIOD) / BAR_PERIOD
        assert amp == pytest.approx(2 * BAR_V0 / np.pi, rel=0.03)
    order = math.log(errs[8] / errs[32]) / math.log(4)
    assert errs[8] > errs[16] > errs[32] and errs[32] < 0.01, errs
    assert 1.7 < order < 2.3, (errs, order)


@pytest.mark.parametrize("dim, ppc", [(2, "[3, 2]"), (3, "[2, 3, 3]"), (3, "[3, 2, 1]")])
def test_points_per_cell_per_axis_fill_the_layer(dim, ppc):
    """``grid.particles_per_cell`` given per axis: n_a points per cell along axis a, on the
    cell-centred lattice, whose volumes add up to the layer's (Σ m J = ρ φ × volume), and the
    geostatic start of the chute carries the layer's weight at the base for every lattice."""
    from segmpm.simulation import Simulation, build_count

    cfg = _seed2d([f"grid.particles_per_cell={ppc}", f"geometry.dimension={dim}",
                   "geometry.width=0.004", "geometry.mirror=false", "segregation.model='none'"])  # fmt: skip
    n_axis = cfg.grid.points_per_axis(dim)
    sim = Simulation(cfg)
    P = sim.engine.points
    g, h = cfg.geometry, cfg.grid.cell_size
    extent = (g.length, g.depth, g.width)[:dim]
    expect = [round(e / h * n) for e, n in zip(extent, n_axis, strict=True)]
    assert P.x.shape[1] == math.prod(expect)
    # the thread policy's estimate (before building) is off by less than one point row
    assert abs(build_count(cfg) - P.x.shape[1]) < P.x.shape[1] / expect[1]
    for a in range(dim):  # the distinct coordinates along each axis: spacing extent / count
        u = np.unique(np.round(P.x[a] / h * 1e9))
        assert u.size == expect[a]
        np.testing.assert_allclose(np.diff(np.sort(u)) * 1e-9 * h, extent[a] / expect[a], rtol=1e-6)
    volume = math.prod(extent)
    rho = cfg.material.solid_fraction * cfg.material.grain_density
    # the points start compressed to the geostatic J: their present volumes fill the layer
    assert (P.mass * P.J).sum() == pytest.approx(rho * volume, rel=1e-12)
    # geostatic σ_yy = −ρ g cos θ (H − y) at every point of every lattice
    gy = 9.81 * math.cos(math.radians(g.slope_deg))
    np.testing.assert_allclose(P.sig[1], -rho * gy * (g.depth - P.x[1]), rtol=1e-9)


@pytest.mark.parametrize("dim", [2, 3])
def test_generic_box_free_fall_is_exact(dim):
    """A stress-free box in free fall, moving along x: symplectic Euler gives v = −g t n and
    y_n = y₀ − g Δt² n(n+1)/2 exactly; x moves with v₀ (periodic, wrapped); no stress."""
    from segmpm.simulation import Simulation

    g, u, dt, n = 9.81, 0.05, 1e-6, 200
    sim = Simulation(_seed2d([
        "scenario.kind='box'", "material.model='linear_elastic'", "geometry.slope_deg=0",
        "geometry.length=0.004", "geometry.depth=0.002", "geometry.width=0.002",
        "geometry.headroom=3", f"scenario.velocity={u}", f"time.dt_max={dt}", "time.dt_min=1e-9",
        f"geometry.dimension={dim}", "grid.engine='generic'", "segregation.model='none'",
    ]))  # fmt: skip
    P = sim.engine.points
    x0 = P.x.copy()
    status, _, steps = sim.advance(1.0, n)
    assert status == 0 and steps == n
    t = n * dt
    np.testing.assert_allclose(P.v[1], -g * t, rtol=1e-12)
    np.testing.assert_allclose(P.v[0], u, rtol=1e-12)
    np.testing.assert_allclose(P.x[1], x0[1] - g * dt * dt * n * (n + 1) / 2, rtol=0, atol=1e-14)
    np.testing.assert_allclose(P.x[0], (x0[0] + u * t) % 0.004, rtol=0, atol=1e-14)
    if dim == 3:  # no motion across: zero to round-off of the partition of unity
        assert np.abs(P.v[2]).max() < 1e-12 * g * t
    assert np.max(np.abs(P.sig)) < 1e-9


def _generic_box(dim, extra=()):
    """A floating periodic box on the generic kernels (docs/model.md §3): no gravity, linear
    elastic, open above, below and (3-D) across."""
    return _seed2d([
        "scenario.kind='box'", "material.model='linear_elastic'", "time.gravity=0",
        "geometry.width=0.002", f"geometry.dimension={dim}", "grid.engine='generic'",
        "segregation.model='none'", *extra,
    ])  # fmt: skip


@pytest.mark.parametrize("dim", [2, 3])
def test_generic_periodic_box_conserves_momentum_and_p2g_mass_is_exact(dim):
    """A free periodic box with a random, non-uniform motion (so it has stresses) keeps its
    momentum to round-off: the internal forces −Σ V σ·∇w sum to zero by the partition of unity,
    and no boundary acts. P2G then puts exactly the points' mass on the grid."""
    from segmpm.engine.helpers import counting_sort
    from segmpm.simulation import Simulation

    sim = Simulation(_generic_box(dim, [
        "geometry.length=0.004", "geometry.depth=0.003", "scenario.velocity=0.3",
    ]))  # fmt: skip
    P = sim.engine.points
    rng = np.random.default_rng(12345)
    P.v[:] += rng.normal(scale=0.05, size=P.v.shape)
    p0 = (P.mass * P.v).sum(axis=1)
    status, _, steps = sim.advance(1.0, 500)
    assert status == 0 and steps == 500
    p1 = (P.mass * P.v).sum(axis=1)
    scale = np.sum(P.mass * np.sqrt((P.v**2).sum(axis=0)))
    assert np.max(np.abs(p1 - p0)) < 1e-12 * scale, (p1 - p0) / scale
    assert np.max(np.abs(P.sig)) > 0  # the test exercised internal forces
    st, k = sim.engine, sim.kernels
    G = st.grid
    k.slab_index(P, st.prm, G.slab_start.shape[0] - 1)
    counting_sort(P.cursor, G.slab_start, G.order, 1)
    k.p2g(P, G, st.prm, False)
    assert abs(G.nodes[..., k.F_M].sum() - P.mass.sum()) < 1e-14 * P.mass.sum()


@pytest.mark.parametrize("dim", [2, 3])
def test_generic_points_wrap_across_the_periodic_boundary(dim):
    """A stress-free box moving at u along x wraps through x = L: every point stays in [0, L),
    sits at (x₀ + u t) mod L, and after one period L/u is back where it started; the other
    coordinates do not move."""
    from segmpm.simulation import Simulation

    L, u = 0.004, 0.5
    sim = Simulation(_generic_box(dim, [
        f"geometry.length={L}", "geometry.depth=0.002", f"scenario.velocity={u}",
    ]))  # fmt: skip
    P = sim.engine.points
    x0 = P.x.copy()
    T = L / u
    for j in range(1, 9):
        sim.advance_to(j * T / 8)
        assert np.all((P.x[0] >= 0) & (P.x[0] < L))
        d = np.abs(P.x[0] - (x0[0] + u * sim.time) % L)
        assert np.max(np.minimum(d, L - d)) < 1e-12
    np.testing.assert_allclose(P.x[1:], x0[1:], rtol=0, atol=1e-15)
    d = np.abs(P.x[0] - x0[0])
    assert np.max(np.minimum(d, L - d)) < 1e-12


@pytest.mark.parametrize("dim", [2, 3])
def test_generic_periodic_wave_period_is_second_order(dim):
    """A standing longitudinal wave v = v₀ sin(2πx) in a periodic elastic box (ν = 0, so the
    free faces do not couple: the 1-D period 1/√(E/ρ) is exact): quadratic B-splines with APIC
    converge at second order in h, in 3-D as in 2-D (the order's bounds of the former plane-strain engine's test)."""
    from segmpm.simulation import Simulation

    errs = {}
    period = 1.0 / math.sqrt(BAR_E / BAR_RHO)
    for cells in (8, 16, 32):
        h = 1.0 / cells
        sim = Simulation(_generic_box(dim, [
            f"material.youngs_modulus={BAR_E}", "material.poisson_ratio=0",
            "material.solid_fraction=1", f"material.grain_density={BAR_RHO}",
            "geometry.length=1.0", f"geometry.depth={h}", f"geometry.width={h}",
            f"grid.cell_size={h}", "scenario.velocity=0", "time.cfl=0.2",
            "grid.transfer='apic'",
        ]))  # fmt: skip
        P = sim.engine.points
        P.v[0] = 0.01 * np.sin(2 * np.pi * P.x[0])
        ts, amp = [], []
        for j in range(401):
            sim.advance_to(j * period / 200)
            ts.append(sim.time)
            amp.append(np.sum(P.mass * P.v[0] * np.sin(2 * np.pi * P.x[0])))
        errs[cells] = abs(_zero_crossing_period(np.array(ts), np.array(amp)) - period) / period
    order = math.log(errs[8] / errs[32]) / math.log(4)
    assert errs[8] > errs[16] > errs[32], errs
    assert 1.8 < order < 2.3, (errs, order)
