"""The column model: an x-uniform layer (chute, inclined plane) resolved in depth only.

``scenario.solver = "column"`` replaces the 2-D MPM by a 1-D updated-Lagrangian finite-element
column for layers whose fields depend on the depth coordinate y alone (docs/column.md). The
compiled column is the engine's (``engine/kernels.py``, ``advance_column``); this module holds
its element layout, its bulk-viscosity floor and the plain NumPy reference of one of its steps
(``column_step_np``, in the layout of segmpm.state, which tests/test_column.py translates the
engine's records into). The physics is not copied: every element calls the MPM's own kernels,

* the constitutive law, the engine's material pass (Jiang–Liu elasticity, the yield cap,
  μ(I) or the nonlocal flow rule, the gas state), with the velocity gradient L = [[0, ∂u/∂y],
  [0, ∂v/∂y]];
* the sidewall Coulomb body force with its speed-dependent μ_w(u), ``engine.helpers.sidewall_drag``,
  and the base condition of the MPM grid update;
* the nonlocal fluidity update, the engine's fluidity step, on a one-node-wide periodic
  grid of the MPM's cell size (its nodal diffusion, cut-cell free surface, Dirichlet base and
  local relaxation unchanged);
* the segregation transport, the engine's concentration step, on a one-cell-wide
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

State: the elements are the engine's points (x: (h_c/2, element centre), v: the mean of the
element's nodes, and the point arrays of the MPM); the nodes (rows ``engine.records.COL_*``)
carry position, velocity and lumped mass; both are in checkpoints.
"""

from __future__ import annotations

import numpy as np

from .config import Config
from .engine.records import COL_M, COL_ROWS, COL_U, COL_V, COL_Y
from .materials.params import M_FLU_DT, M_ZETA
from .mpm.params import (
    G_CFL,
    G_CFLOOR,
    G_DTMAX,
    G_GX,
    G_GY,
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
    S_NUMAX,
    S_SMAX,
    S_STEP,
    S_TFLU,
    S_TIME,
    S_TSEG,
)
from .state import State

#: the column's floor on ``material.bulk_viscosity`` (ζ_b as a fraction of ρ c h): the column has
#: no transfer dissipation, and without a volumetric damping its compression modes ring and grow
#: (on the nonlocal seed case within 0.1 s at any Courant number), throwing the top of the layer
#: into the gas state (docs/column.md); 0.05 ρ c h, i.e. 0.1 ρ c Δy, damps them
COLUMN_BULK_VISCOSITY = 0.05


def column_elements(cfg: Config) -> tuple[np.ndarray, np.ndarray]:
    """The column's node heights (N + 1, from the base) and element centres (N): N =
    depth / (h / n_ppc) elements of equal height, at least two."""
    g = cfg.geometry
    ne = max(2, round(g.depth / cfg.grid.point_spacing(g.dimension)[1]))
    y_nodes = np.arange(ne + 1) * (g.depth / ne)
    return y_nodes, 0.5 * (y_nodes[:-1] + y_nodes[1:])


def build_column(cfg: Config) -> State:
    """The column of a chute configuration in the layout of ``column_step_np`` (the engine's
    own set-up is ``engine.setup.build_column``): elements of the MPM's point spacing h/n_ppc over the
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
    return st


# ---------------------------------------------------------------------------------------------
# NumPy reference of one step (for testing the compiled loop)


def column_step_np(arrays: dict[str, np.ndarray], gp: np.ndarray, mp: np.ndarray,
                   ) -> dict[str, np.ndarray]:  # fmt: skip
    """One step of the engine's column (``advance_column``) on copies of the state arrays, written with arrays and
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
    "build_column",
    "column_step_np",
]
