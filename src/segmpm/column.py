"""The column model: an x-uniform layer (chute, inclined plane) resolved in depth only.

``scenario.solver = "column"`` replaces the 2-D MPM by a 1-D updated-Lagrangian finite-element
column for layers whose fields depend on the depth coordinate y alone (docs/column.md). The
physics is not copied: every element calls the MPM's own kernels,

* the constitutive law, ``materials.material_update_var`` (Jiang–Liu elasticity, the yield cap,
  μ(I) or the nonlocal flow rule, the gas state), with the velocity gradient L = [[0, ∂u/∂y],
  [0, ∂v/∂y]];
* the sidewall Coulomb body force with its speed-dependent μ_w(u), ``mpm.boundary.sidewall_drag``,
  and the base condition, ``mpm.boundary.apply_bc``;
* the nonlocal fluidity update, ``mpm.fluidity.fluidity_step``, on a one-node-wide periodic
  grid of the MPM's cell size (its nodal diffusion, cut-cell free surface, Dirichlet base and
  local relaxation unchanged);
* the segregation transport, ``segregation.grid.concentration_step``, on a one-cell-wide
  periodic concentration grid of the MPM's concentration-cell size, the elements acting as its
  material points (the conservative, bound-preserving mapping unchanged).

Discretisation: N two-node linear elements of the MPM's point spacing h/n_ppc (one element per
row of material points: the column holds the same material, row by row; elements of the cell
size h were 0.012 u_s off the MPM in velocity and, on a concentration grid finer than the
elements, blocked every other face of the segregation flux), lumped nodal mass, node 0 on the
base, the top node the free surface (zero traction). Per step, in the order of the
MPM's update-stress-last step: nodal forces from the element stresses, gravity and the sidewall
force → nodal velocities with the base condition → element velocity gradients → element J and
material update → node positions. The time step is the column's own Courant step on its
shortest element, Δt = min(C Δy/(max(c + |v|) + 2 max ν/Δy), C_ν Δy²/(2ν), Δt_max), the
combined wave and diffusion bound of the explicit 1-D scheme (the two limits taken apart were
unstable on the Bagnold layer at C = 0.9), with C_ν the MPM's viscous number and C =
``time.column_courant`` (default 0.9) and the MPM's wave-speed bound c; the bulk viscosity is
at least ``COLUMN_BULK_VISCOSITY`` (the column has no transfer dissipation to damp its
compression modes).

State: the elements are the ``State``'s points (x: (h_c/2, element centre), v: the mean of the
element's nodes, and the point arrays of the MPM); the nodes (``State.nodes``, rows ``COL_*``)
carry position, velocity and lumped mass; both are in checkpoints.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from . import _llvm_options  # noqa: F401  (before any kernel of the loop compiles)
from .config import Config
from .engine.records import COL_M, COL_ROWS, COL_U, COL_V, COL_Y
from .materials import (
    VAR_ELASTIC,
    VAR_FEI_LINEAR,
    VAR_FEI_POWER,
    VAR_NGF,
    material_update_var,
    material_variant,
)
from .materials.params import M_FLU_DT, M_ZETA
from .mpm.boundary import apply_bc, sidewall_drag
from .mpm.fluidity import fluidity_step
from .mpm.params import (
    G_CFL,
    G_CFLOOR,
    G_DTMAX,
    G_DTMIN,
    G_GX,
    G_GY,
    G_H,
    G_LX,
    G_NY,
    G_RAMP,
    G_SIDEWALL,
    G_SW_SLOW,
    G_SW_SPEED,
    G_VISC,
    G_Y0,
    S_DT,
    S_NFLU,
    S_NSEG,
    S_NUMAX,
    S_SMAX,
    S_STEP,
    S_TFLU,
    S_TIME,
    S_TSEG,
    ST_DT_COLLAPSE,
    ST_LEFT_GRID,
    ST_NONFINITE,
    ST_OK,
)
from .segregation.closures import P_DT_TARGET, P_MODEL
from .segregation.grid import concentration_step
from .state import State

#: the column's floor on ``material.bulk_viscosity`` (ζ_b as a fraction of ρ c h): the column has
#: no transfer dissipation, and without a volumetric damping its compression modes ring and grow
#: (on the nonlocal seed case within 0.1 s at any Courant number), throwing the top of the layer
#: into the gas state (docs/column.md); 0.05 ρ c h, i.e. 0.1 ρ c Δy, damps them
COLUMN_BULK_VISCOSITY = 0.05

#: rows of the node record ``State.nodes`` (COL_ROWS, N + 1): ``engine.records.COL_*``, shared
#: with the generic engine's column (position y, velocities u and v, lumped mass per metre of z)


@njit(cache=True, error_model="numpy", inline="always")
def _elements(var, dt, nodes, v, J, eps, sig, phi, gf, diag, s_int, g_int, mp):
    """The material update of every element from the new nodal velocities (variant ``var``, a
    constant once inlined): strain, stress, diagnostics (``diag`` rows 0–5, the signal speed
    c + |v| in row 4) and the segregation integrals. A loop without calls or reductions over
    unsigned indices, so that it vectorises like the MPM's material pass; ``_check`` reduces."""
    for u in range(np.uint64(J.shape[0])):
        dy = nodes[COL_Y, u + 1] - nodes[COL_Y, u]
        u0 = nodes[COL_U, u]
        u1 = nodes[COL_U, u + 1]
        w0 = nodes[COL_V, u]
        w1 = nodes[COL_V, u + 1]
        l01 = (u1 - u0) / dy
        l11 = (w1 - w0) / dy
        Jn = J[u] * (1.0 + dt * l11)
        J[u] = Jn
        r = material_update_var(var, mp, 0.0, l01, 0.0, l11, dt, eps[0, u], eps[1, u],
                                eps[2, u], eps[3, u], Jn, phi[u], gf[u])  # fmt: skip
        eps[0, u] = r[0]
        eps[1, u] = r[1]
        eps[2, u] = r[2]
        eps[3, u] = r[3]
        sig[0, u] = r[4]
        sig[1, u] = r[5]
        sig[2, u] = r[6]
        sig[3, u] = r[7]
        diag[0, u] = r[8]
        diag[1, u] = r[9]
        diag[2, u] = r[10]
        diag[3, u] = r[11]
        s_int[u] += r[11] * dt
        g_int[u] += r[9] * dt
        ve = 0.5 * (u0 + u1)
        we = 0.5 * (w0 + w1)
        v[0, u] = ve
        v[1, u] = we
        diag[4, u] = r[12] + math.sqrt(ve * ve + we * we)
        diag[5, u] = r[13]


@njit(cache=True, error_model="numpy", inline="always")
def _check(J, sig, diag):
    """(max c + |v|, max ν, first element whose signal speed or stress is not finite or whose
    J ≤ 0, else −1)."""
    smax = 0.0
    numax = 0.0
    bad = -1
    for e in range(J.shape[0]):
        s = diag[4, e]
        smax = max(smax, s)
        numax = max(numax, diag[5, e])
        if bad < 0 and not (
            math.isfinite(s)
            and math.isfinite(sig[0, e] + sig[1, e] + sig[2, e] + sig[3, e])
            and J[e] > 0.0
        ):
            bad = e
    return smax, numax, bad


@njit(cache=True, error_model="numpy", inline="always")
def node_velocity(j, fx, fy, vp, nodes, dt, gx, gy, sw, sw0, uw, lx):
    """The new velocity of node j from its net internal force per unit width (fx, fy), gravity
    and the sidewall force on vp = Σ V p of its half elements."""
    im = 1.0 / nodes[COL_M, j]
    u = nodes[COL_U, j] + dt * (lx * fx * im + gx)
    w = nodes[COL_V, j] + dt * (lx * fy * im + gy)
    if (sw > 0.0 or sw0 > 0.0) and vp > 0.0:
        u, w = sidewall_drag(u, w, sw, sw0, uw, dt, vp, im)
    nodes[COL_U, j] = u
    nodes[COL_V, j] = w


@njit(cache=True, error_model="numpy", inline="always")
def _nodes(nodes, sig, vol0, J, pres, gp, dt, ramp, lx):
    """Nodal velocities over one step: internal force lx (σ_above − σ_below) (zero traction
    above the top node), gravity, the sidewall force on Σ V p of the node's half elements; then
    the base condition on node 0, the only node on the base plane. The interior nodes run as a
    loop without calls (unsigned indices), so that it vectorises."""
    ne = nodes.shape[1] - 1
    gx = gp[G_GX] * ramp
    gy = gp[G_GY]
    sw = gp[G_SIDEWALL] * ramp
    uw = gp[G_SW_SPEED]
    sw0 = gp[G_SW_SLOW] * ramp if uw > 0.0 else sw
    for k in range(np.uint64(ne - 1)):
        j = k + np.uint64(1)
        b = k
        fx = sig[2, j] - sig[2, b]
        fy = sig[1, j] - sig[1, b]
        vp = 0.5 * vol0[j] * J[j] * pres[j] + 0.5 * vol0[b] * J[b] * pres[b]
        node_velocity(j, fx, fy, vp, nodes, dt, gx, gy, sw, sw0, uw, lx)
    # the top node (the free surface: only the element below) and the base node
    b = ne - 1
    node_velocity(ne, -sig[2, b], -sig[1, b], 0.5 * vol0[b] * J[b] * pres[b], nodes, dt, gx, gy, sw, sw0,
          uw, lx)  # fmt: skip
    node_velocity(0, sig[2, 0], sig[1, 0], 0.5 * vol0[0] * J[0] * pres[0], nodes, dt, gx, gy, sw, sw0,
          uw, lx)  # fmt: skip
    nodes[COL_U, 0], nodes[COL_V, 0] = apply_bc(gp, 0.5 * lx, nodes[COL_Y, 0], nodes[COL_U, 0],
                                                nodes[COL_V, 0])  # fmt: skip


@njit(cache=True, error_model="numpy", parallel=True, fastmath={"contract"})
def advance_column(x, v, mass, vol0, J, eps, sig, phi, gf, diag, s_int, g_int, nodes, seg_vol,
                   gp, mp, sc, fw, seg_prm, cg, seg_work, t_stop, max_steps):  # fmt: skip
    """Advance the column to ``t_stop`` (exactly) or by ``max_steps`` steps (the contract of
    ``mpm.step.advance``): returns (status, element index, steps taken). ``seg_vol``: the
    elements' reference volumes on the concentration grid's one-cell width."""
    n = J.shape[0]
    lx = gp[G_LX]
    var = material_variant(mp)
    nonlocal_on = var == VAR_NGF
    y_max = gp[G_Y0] + (gp[G_NY] - 1.5) * gp[G_H]
    steps = 0
    while steps < max_steps and sc[S_TIME] < t_stop:
        t = sc[S_TIME]
        dymin = math.inf
        for e in range(n):
            dymin = min(dymin, nodes[COL_Y, e + 1] - nodes[COL_Y, e])
        dt = gp[G_DTMAX]
        smax = max(sc[S_SMAX], gp[G_CFLOOR])
        # the combined wave and diffusion bound of the explicit 1-D scheme (each limit alone was
        # unstable together with the other: docs/column.md)
        rate = smax + 2.0 * sc[S_NUMAX] / dymin
        if rate > 0.0:
            dt = min(dt, gp[G_CFL] * dymin / rate)
        if sc[S_NUMAX] > 0.0:
            dt = min(dt, gp[G_VISC] * dymin * dymin / (2.0 * sc[S_NUMAX]))
        if not (dt >= gp[G_DTMIN]):
            return ST_DT_COLLAPSE, -1, steps
        if t + dt * 1.000001 >= t_stop:
            dt = t_stop - t
        ramp = 1.0
        if gp[G_RAMP] > 0.0:
            ramp = min(1.0, (t + dt) / gp[G_RAMP])

        # each pass is a one-block parallel region: Numba's parallel lowering hands the arrays to
        # the region as distinct arguments, and only then does LLVM vectorise the loops (the
        # material pass 3× faster than the same loop inline: docs/column.md)
        for _ in prange(1):
            _nodes(nodes, sig, vol0, J, diag[0], gp, dt, ramp, lx)
        for _ in prange(1):
            if var == VAR_FEI_LINEAR:
                _elements(VAR_FEI_LINEAR, dt, nodes, v, J, eps, sig, phi, gf, diag, s_int, g_int,
                          mp)  # fmt: skip
            elif var == VAR_NGF:
                _elements(VAR_NGF, dt, nodes, v, J, eps, sig, phi, gf, diag, s_int, g_int, mp)
            elif var == VAR_FEI_POWER:
                _elements(VAR_FEI_POWER, dt, nodes, v, J, eps, sig, phi, gf, diag, s_int, g_int,
                          mp)  # fmt: skip
            else:
                _elements(VAR_ELASTIC, dt, nodes, v, J, eps, sig, phi, gf, diag, s_int, g_int, mp)
        smax, numax, bad = _check(J, sig, diag)
        # separate passes, each vectorisable (fused, the position update carries a dependence
        # from element to element and the step was slower)
        for j in range(n + 1):
            nodes[COL_Y, j] += dt * nodes[COL_V, j]
        for e in range(n):
            x[1, e] = 0.5 * (nodes[COL_Y, e] + nodes[COL_Y, e + 1])

        sc[S_TIME] = t + dt
        sc[S_STEP] += 1.0
        sc[S_DT] = dt
        sc[S_TSEG] += dt
        steps += 1
        sc[S_SMAX] = smax
        sc[S_NUMAX] = numax
        if bad >= 0:
            return ST_NONFINITE, bad, steps
        if not (nodes[COL_Y, n] < y_max):
            return (ST_LEFT_GRID if math.isfinite(nodes[COL_Y, n]) else ST_NONFINITE), n - 1, steps
        if nonlocal_on:
            sc[S_TFLU] += dt
            if sc[S_TFLU] >= mp[M_FLU_DT] * (1.0 - 1e-12):
                fluidity_step(x, mass, phi, sig, diag[0], gf, gp, mp, fw, sc[S_TFLU])
                sc[S_TFLU] = 0.0
                sc[S_NFLU] += 1.0
        if sc[S_TSEG] >= seg_prm[P_DT_TARGET] * (1.0 - 1e-12):
            if seg_prm[P_MODEL] != 0.0:
                concentration_step(x[0], x[1], seg_vol, phi, s_int, g_int, sc[S_TSEG], cg,
                                   seg_prm, seg_work)  # fmt: skip
                sc[S_NSEG] += 1.0
            else:
                s_int[:] = 0.0
                g_int[:] = 0.0
            sc[S_TSEG] = 0.0
    return ST_OK, -1, steps


# ---------------------------------------------------------------------------------------------
# set-up


def column_elements(cfg: Config) -> tuple[np.ndarray, np.ndarray]:
    """The column's node heights (N + 1, from the base) and element centres (N): N =
    depth / (h / n_ppc) elements of equal height, at least two."""
    g = cfg.geometry
    ne = max(2, round(g.depth / (cfg.grid.cell_size / cfg.grid.particles_per_cell)))
    y_nodes = np.arange(ne + 1) * (g.depth / ne)
    return y_nodes, 0.5 * (y_nodes[:-1] + y_nodes[1:])


def build_column(cfg: Config) -> State:
    """The column of a chute configuration: elements of the MPM's point spacing h/n_ppc over the
    depth H (round(H n_ppc/h) of them), nodes from the base (y = 0) to the free surface, the geostatic
    initial state of the MPM builder, a one-node-wide periodic fluidity grid of cell h and a
    one-cell-wide periodic concentration grid; ``gp[G_CFL]`` holds the column's Courant
    number, the material record the bulk-viscosity floor ``COLUMN_BULK_VISCOSITY``."""
    from .materials import pack_material
    from .scenarios.builders import GHOST, _initial_strain, _ny, grid_record, wave_speed_floor
    from .segregation import conc_cell_size, make_conc_grid, pack_params

    g = cfg.geometry
    h = cfg.grid.cell_size
    y_nodes, yc = column_elements(cfg)
    ne = yc.size
    dy = g.depth / ne
    gp = grid_record(cfg, x0=0.0, nx=1, y0=-GHOST * h, ny=_ny(g.depth * (1 + g.headroom), h),
                     periodic=True, base=cfg.boundary.base)  # fmt: skip
    lx = h  # the column's width in x: the fluidity grid's one periodic cell
    mp = pack_material(cfg)
    mp[M_ZETA] = max(mp[M_ZETA], COLUMN_BULK_VISCOSITY)
    rho = cfg.material.solid_fraction * cfg.material.grain_density
    p_yy = rho * (-gp[G_GY]) * (g.depth - yc)
    eps, J = _initial_strain(cfg, mp, p_yy)
    vol0 = np.full(ne, dy * lx) / J
    mass = rho * vol0
    hc = conc_cell_size(cfg)
    x = np.stack([np.full(ne, 0.5 * hc), yc])
    st = State.from_points(x, np.zeros((2, ne)), mass, vol0, J, eps,
                           np.full(ne, cfg.mixture.phi_small_initial), gp, mp)  # fmt: skip
    nodes = np.zeros((COL_ROWS, ne + 1))
    nodes[COL_Y] = y_nodes
    nodes[COL_M, :-1] += 0.5 * mass
    nodes[COL_M, 1:] += 0.5 * mass
    st.nodes = nodes
    gp[G_CFLOOR] = wave_speed_floor(cfg, mp, float(np.max(p_yy)))
    gp[G_CFL] = cfg.time.column_courant
    st.cg = make_conc_grid(0.0, hc, 0.0, gp[G_Y0] + (gp[G_NY] - 1) * h, hc, True)
    st.seg_prm = pack_params(cfg, (gp[G_GX], gp[G_GY]))
    st.allocate_work()
    st.work["seg_vol"] = vol0 * (hc / lx)
    return st


# ---------------------------------------------------------------------------------------------
# NumPy reference of one step (for testing the compiled loop)


def column_step_np(arrays: dict[str, np.ndarray], gp: np.ndarray, mp: np.ndarray,
                   ) -> dict[str, np.ndarray]:  # fmt: skip
    """One step of :func:`advance_column` on copies of the state arrays, written with arrays and
    the NumPy twins of the shared kernels (material law, base condition, fluidity update);
    returns the new arrays. The segregation subcycle is not taken (its twin is tested on its
    own, ``segregation.reference``)."""
    from .materials import KIND_FEI2016_NGF, material_update_np
    from .materials.params import M_KIND
    from .mpm.fluidity import fluidity_step_np
    from .mpm.reference import apply_bc_np

    s = {k: np.array(v, dtype=np.float64, copy=True) for k, v in arrays.items()}
    nodes, sig, J, sc = s["nodes"], s["sig"], s["J"], s["sc"]
    lx = gp[G_LX]
    dy = np.diff(nodes[COL_Y])
    dt = gp[G_DTMAX]
    smax = max(sc[S_SMAX], gp[G_CFLOOR])
    rate = smax + 2.0 * sc[S_NUMAX] / dy.min()
    if rate > 0:
        dt = min(dt, gp[G_CFL] * dy.min() / rate)
    if sc[S_NUMAX] > 0:
        dt = min(dt, gp[G_VISC] * dy.min() ** 2 / (2 * sc[S_NUMAX]))
    t = sc[S_TIME]
    ramp = min(1.0, (t + dt) / gp[G_RAMP]) if gp[G_RAMP] > 0 else 1.0
    # nodal forces: the element above minus the element below (zero traction at the top)
    pad = np.zeros((4, 1))
    above = np.concatenate([sig, pad], axis=1)
    below = np.concatenate([pad, sig], axis=1)
    vp_e = 0.5 * s["vol0"] * J * s["diag"][0]
    vp = np.concatenate([vp_e, [0.0]]) + np.concatenate([[0.0], vp_e])
    m = nodes[COL_M]
    u = nodes[COL_U] + dt * (lx * (above[2] - below[2]) / m + gp[G_GX] * ramp)
    w = nodes[COL_V] + dt * (lx * (above[1] - below[1]) / m + gp[G_GY])
    sw = gp[G_SIDEWALL] * ramp
    uw = gp[G_SW_SPEED]
    sw0 = gp[G_SW_SLOW] * ramp if uw > 0 else sw
    if sw > 0 or sw0 > 0:
        speed = np.hypot(u, w)
        fac = sw0 + (sw - sw0) * speed / (speed + uw) if uw > 0 else sw
        dvmax = np.where(vp > 0, dt * fac * vp / m, 0.0)
        f = np.where(speed <= dvmax, 0.0, 1.0 - dvmax / np.where(speed > 0, speed, 1.0))
        u, w = u * f, w * f
    u, w = apply_bc_np(gp, np.full_like(u, 0.5 * lx), nodes[COL_Y], u, w)
    nodes[COL_U], nodes[COL_V] = u, w
    L = np.zeros((dy.shape[0], 2, 2))
    L[:, 0, 1] = np.diff(u) / dy
    L[:, 1, 1] = np.diff(w) / dy
    s["J"] = J * (1 + dt * L[:, 1, 1])
    eps_new, sig_new, p, gdot, inert, S, cw, nu = material_update_np(
        mp, L, dt, s["eps"].T, s["J"], s["phi"], s["gf"]
    )
    s["eps"], s["sig"] = eps_new.T.copy(), sig_new.T.copy()
    v = s["v"]
    v[0], v[1] = 0.5 * (u[:-1] + u[1:]), 0.5 * (w[:-1] + w[1:])
    s["diag"][0], s["diag"][1], s["diag"][2], s["diag"][3] = p, gdot, inert, S
    s["diag"][4] = cw + np.hypot(v[0], v[1])
    s["diag"][5] = nu
    s["s_int"] += S * dt
    s["g_int"] += gdot * dt
    nodes[COL_Y] += dt * w
    s["x"][1] = 0.5 * (nodes[COL_Y, :-1] + nodes[COL_Y, 1:])
    sc[S_TIME] = t + dt
    sc[S_STEP] += 1
    sc[S_DT] = dt
    sc[S_TSEG] += dt
    sc[S_SMAX] = s["diag"][4].max()
    sc[S_NUMAX] = s["diag"][5].max()
    if mp[M_KIND] == KIND_FEI2016_NGF:
        sc[S_TFLU] += dt
        if sc[S_TFLU] >= mp[M_FLU_DT] * (1.0 - 1e-12):
            s["gf"], _ = fluidity_step_np(s["x"], s["mass"], s["phi"], s["sig"], s["diag"][0],
                                          s["gf"], gp, mp, sc[S_TFLU])  # fmt: skip
            sc[S_TFLU] = 0.0
            sc[S_NFLU] += 1
    return s


__all__ = [
    "COLUMN_BULK_VISCOSITY",
    "COL_M",
    "COL_U",
    "COL_V",
    "COL_Y",
    "advance_column",
    "build_column",
    "column_step_np",
]
