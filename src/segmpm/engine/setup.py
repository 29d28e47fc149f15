"""Scenarios of the dimension-generic engine: points, grid and records from a configuration.

* ``chute``: a periodic layer of depth H on a slope θ, no-slip (or frictional) base at y = 0.
  2-D: the sidewalls are the Coulomb body force of Jop et al. 2005. 3-D: two resolved walls at
  z = 0 and z = W with Coulomb friction μ_w = ``boundary.sidewall_friction`` on the nodes at and
  beyond them (with ``boundary.sidewall_slip_speed`` u_w > 0, the speed-dependent law
  μ_w(u) = μ_w0 + (μ_w − μ_w0) u/(u + u_w) of the sliding speed u, μ_w0 =
  ``boundary.sidewall_friction_slow``; K_w is not used: the walls' normal stress is resolved); with ``geometry.mirror`` only 0 ≤ z ≤ W/2 is modelled, with a symmetry plane at
  z = W/2.
* ``collapse``: 2-D the column L₀ × H₀ against the wall x = 0; 3-D an axisymmetric column of
  radius r₀ = ``geometry.column_width`` and height H₀ = ``geometry.column_height`` on a rough base,
  one quarter of it, with symmetry planes x = 0 and z = 0, in the domain [0, length]².
* ``box`` and ``bar``: the verification bodies (a periodic floating layer; an elastic bar
  clamped at x = 0), in 3-D with the cross-section ``geometry.depth`` × ``geometry.width``.

docs/architecture.md gives the layout, docs/model.md the physics.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..config import Config
from ..materials import pack_material
from ..materials.params import KIND_FEI2016_NGF, M_KIND
from ..mpm.params import TRANSFER_AFLIP, TRANSFER_APIC, TRANSFER_FLIP
from ..scenarios.builders import (
    GHOST,
    _initial_strain,
    gravity_vector,
    lattice,
    wave_speed_floor,
)
from .records import (
    CLOCK,
    COL_M,
    COL_ROWS,
    COL_Y,
    CONC,
    PARAMS,
    PLANE_CODES,
    POINT_STATE,
    Grid,
    Points,
    Segregation,
    material_record,
)


@dataclass
class EngineState:
    """Everything a run of the generic engine holds: points, grid, records."""

    dim: int
    points: Points
    grid: Grid
    prm: np.ndarray  # PARAMS, one element
    mp: np.ndarray  # the packed material (``mat`` is its named view)
    clock: np.ndarray  # CLOCK, one element
    seg: Segregation  # the concentration grid, closure parameters and scratch
    #: the column model (``scenario.solver = "column"``): its nodes (COL_ROWS, N + 1), and the
    #: elements as the concentration step's points (``vol0`` on the concentration cell's width)
    nodes: np.ndarray | None = None
    seg_points: Points | None = None

    @property
    def mat(self) -> np.ndarray:
        """The named view of ``mp`` (MATERIAL, one element)."""
        return material_record(self.mp)

    @property
    def n(self) -> int:
        return int(self.points.mass.shape[0])

    def arrays(self) -> dict[str, np.ndarray]:
        """The physical state by name, as a checkpoint holds it (views, not copies): the point
        arrays of POINT_STATE, ``clock`` (the CLOCK record's bytes) and the column's ``nodes``."""
        out = {k: getattr(self.points, k) for k in POINT_STATE}
        out["clock"] = self.clock.view(np.uint8)
        if self.nodes is not None:
            out["nodes"] = self.nodes
        return out


def _params(cfg: Config, dim: int, origin, nodes, periodic: bool) -> np.ndarray:
    h = cfg.grid.cell_size
    b = cfg.boundary
    prm = np.zeros(1, dtype=PARAMS)  # a one-element array: compiled kernels take arrays
    prm["dim"] = dim
    prm["h"] = h
    prm["origin"][:] = origin
    prm["nodes"][:] = nodes
    prm["periodic_x"] = 1 if periodic else 0
    prm["length_x"] = nodes[0] * h if periodic else 0.0
    gx, gy = gravity_vector(cfg)
    prm["gravity"][:] = (gx, gy, 0.0)
    prm["ramp"] = b.ramp_time
    prm["transfer"] = {"apic": TRANSFER_APIC, "aflip": TRANSFER_AFLIP, "flip": TRANSFER_FLIP}[
        cfg.grid.transfer
    ]
    prm["flip"] = cfg.grid.flip_fraction
    prm["cfl"] = cfg.time.cfl
    prm["visc"] = cfg.time.viscous_number
    prm["dt_max"] = cfg.time.dt_max
    prm["dt_min"] = cfg.time.dt_min
    prm["base_kind"] = PLANE_CODES[b.base]
    prm["base_y"] = 0.0
    prm["base_mu"] = b.base_friction
    prm["images"] = 1 if b.wall_images else 0
    vs = cfg.grid.volumetric_smoothing
    auto = dim == 3 and cfg.material.rheology == "nonlocal"  # docs/model.md §2: measured there
    prm["dilatation"] = 1 if (vs == "on" or (vs == "auto" and auto)) else 0
    return prm


def _sidewall_force(cfg: Config, prm: np.ndarray) -> None:
    """2-D: the sidewall Coulomb body force 2 μ_w K_w / W (docs/model.md §2)."""
    b = cfg.boundary
    if b.sidewall_friction > 0 or b.sidewall_slip_speed > 0:
        k = 2.0 * b.wall_normal_stress_ratio / cfg.geometry.width
        prm["sidewall"] = k * b.sidewall_friction
        if b.sidewall_slip_speed > 0:
            prm["sidewall_slow"] = k * b.sidewall_friction_slow
            prm["sidewall_speed"] = b.sidewall_slip_speed


def _ny(top: float, h: float) -> int:
    return int(math.ceil(top / h)) + 2 * GHOST + 1


def _nz_walls(width: float, h: float) -> int:
    """Nodes across [−GHOST h, width + GHOST h] (the walls lie on node planes)."""
    return int(round(width / h)) + 2 * GHOST + 1


def build_chute(cfg: Config, dim: int) -> tuple[np.ndarray, float, np.ndarray]:
    g = cfg.geometry
    h = cfg.grid.cell_size
    nx = round(g.length / h)
    s = cfg.grid.point_spacing(dim)
    ny = _ny(g.depth * (1 + g.headroom), h)
    if dim == 2:
        x, vol = lattice((0.0, 0.0), (nx * h, g.depth), s)
        prm = _params(cfg, 2, (0.0, -GHOST * h, 0.0), (nx, ny, 1), True)
        _sidewall_force(cfg, prm)
        return x, vol, prm
    wm = g.width / 2 if g.mirror else g.width
    if abs(wm / h - round(wm / h)) > 1e-6 * max(1.0, wm / h):
        raise ValueError(f"the modelled width {wm} must be a whole number of cells of {h}")
    x, vol = lattice((0.0, 0.0, 0.0), (nx * h, g.depth, wm), s)
    prm = _params(cfg, 3, (0.0, -GHOST * h, -GHOST * h), (nx, ny, _nz_walls(wm, h)), True)
    b = cfg.boundary
    mu = b.sidewall_friction
    wall = PLANE_CODES["friction"] if (mu > 0 or b.sidewall_slip_speed > 0) else PLANE_CODES["slip"]
    if b.sidewall_slip_speed > 0:  # the speed-dependent wall law of the grain calibration
        prm["wall_mu0"], prm["wall_speed"] = b.sidewall_friction_slow, b.sidewall_slip_speed
    prm["zlo_kind"], prm["zlo"], prm["zlo_mu"] = wall, 0.0, mu
    prm["zhi_kind"], prm["zhi"], prm["zhi_mu"] = (
        (PLANE_CODES["symmetry"], wm, 0.0) if g.mirror else (wall, wm, mu)
    )
    return x, vol, prm


def build_collapse(cfg: Config, dim: int) -> tuple[np.ndarray, float, np.ndarray]:
    g = cfg.geometry
    h = cfg.grid.cell_size
    s = cfg.grid.point_spacing(dim)
    nxc = int(math.ceil(g.length / h))
    ny = _ny(g.column_height * (1 + g.headroom), h)
    walls = PLANE_CODES[cfg.boundary.walls]
    if dim == 2:
        x, vol = lattice((0.0, 0.0), (g.column_width, g.column_height), s)
        prm = _params(cfg, 2, (-GHOST * h, -GHOST * h, 0.0), (nxc + 2 * GHOST + 1, ny, 1), False)
        _sidewall_force(cfg, prm)
        prm["xlo_kind"], prm["xlo"], prm["xlo_mu"] = walls, 0.0, cfg.boundary.wall_friction
        prm["xhi_kind"], prm["xhi"], prm["xhi_mu"] = walls, nxc * h, cfg.boundary.wall_friction
        return x, vol, prm
    r0 = g.column_width
    x, vol = lattice((0.0, 0.0, 0.0), (r0, g.column_height, r0), s)
    keep = x[0] ** 2 + x[2] ** 2 <= r0 * r0
    x = np.ascontiguousarray(x[:, keep])
    n3 = nxc + 2 * GHOST + 1
    prm = _params(cfg, 3, (-GHOST * h, -GHOST * h, -GHOST * h), (n3, ny, n3), False)
    sym = PLANE_CODES["symmetry"]
    prm["xlo_kind"], prm["xlo"] = sym, 0.0
    prm["zlo_kind"], prm["zlo"] = sym, 0.0
    # the far ends: open (the domain is sized so that the deposit stays inside)
    return x, vol, prm


def build_box(cfg: Config, dim: int) -> tuple[np.ndarray, float, np.ndarray]:
    """Periodic layer of depth H floating in the middle of the grid (no base, no sidewall
    force): free fall and momentum tests (the 2-D reference builder's box). 3-D: across
    0 ≤ z ≤ ``geometry.width`` between open planes, with ``geometry.headroom`` × W of grid on
    either side."""
    g = cfg.geometry
    h = cfg.grid.cell_size
    nx = round(g.length / h)
    s = cfg.grid.point_spacing(dim)
    bottom = g.headroom * g.depth
    ny = _ny(g.depth * (1 + 2 * g.headroom), h)
    if dim == 2:
        x, vol = lattice((0.0, bottom), (nx * h, bottom + g.depth), s)
        prm = _params(cfg, 2, (0.0, -GHOST * h, 0.0), (nx, ny, 1), True)
        prm["base_kind"] = PLANE_CODES["open"]
        return x, vol, prm
    pad = int(math.ceil(g.headroom * g.width / h)) + GHOST
    x, vol = lattice((0.0, bottom, 0.0), (nx * h, bottom + g.depth, g.width), s)
    nz = int(math.ceil(g.width / h)) + 2 * pad + 1
    prm = _params(cfg, 3, (0.0, -GHOST * h, -pad * h), (nx, ny, nz), True)
    prm["zlo_kind"] = prm["zhi_kind"] = prm["base_kind"] = PLANE_CODES["open"]
    return x, vol, prm


def build_bar(cfg: Config, dim: int) -> tuple[np.ndarray, float, np.ndarray]:
    """Elastic bar of length L along x, clamped at x = 0 (a no-slip plane), free at x = L; no
    gravity, no sidewall force (docs/model.md §3). 3-D: its cross-section is ``geometry.depth``
    × ``geometry.width``, free on every side."""
    g = cfg.geometry
    h = cfg.grid.cell_size
    s = cfg.grid.point_spacing(dim)
    nxc = int(math.ceil(g.length * (1 + g.headroom) / h))
    origin = (-GHOST * h, -GHOST * h, -GHOST * h if dim == 3 else 0.0)
    ny = _ny(g.depth, h)
    if dim == 2:
        x, vol = lattice((0.0, 0.0), (g.length, g.depth), s)
        prm = _params(cfg, 2, origin, (nxc + 2 * GHOST + 1, ny, 1), False)
    else:
        x, vol = lattice((0.0, 0.0, 0.0), (g.length, g.depth, g.width), s)
        nz = int(math.ceil(g.width / h)) + 2 * GHOST + 1
        prm = _params(cfg, 3, origin, (nxc + 2 * GHOST + 1, ny, nz), False)
        prm["zlo_kind"] = prm["zhi_kind"] = PLANE_CODES["open"]
    prm["base_kind"] = PLANE_CODES["open"]
    prm["xlo_kind"], prm["xlo"] = PLANE_CODES["noslip"], 0.0
    prm["gravity"][:] = 0.0
    return x, vol, prm


def initial_velocity(cfg: Config, x: np.ndarray) -> np.ndarray:
    """The initial velocity of the points at ``x`` (D, N): ``scenario.velocity`` v₀ along x for
    the box, the bar's first mode v₀ sin(πx/2L); at rest otherwise."""
    v = np.zeros_like(x)
    kind = cfg.scenario.kind
    if kind == "box":
        v[0] = cfg.scenario.velocity
    elif kind == "bar":
        v[0] = cfg.scenario.velocity * np.sin(np.pi * x[0] / (2 * cfg.geometry.length))
    return v


BUILDERS = {"chute": build_chute, "collapse": build_collapse, "box": build_box, "bar": build_bar}


def segregation_grid(cfg: Config, prm: np.ndarray, x: np.ndarray, nwork: int) -> Segregation:
    """The extra Eulerian grid over the MPM grid (as the 2-D reference builder's,
    scenarios.builders.attach_segregation), closed in z between the walls (3-D), with cells of
    ``segregation.cell_size`` (default h/2) and one ghost layer on the closed sides."""
    from ..segregation import conc_cell_size, make_conc_grid, pack_params

    pr = prm[0]
    h = float(pr["h"])
    hc = conc_cell_size(cfg)
    periodic = bool(pr["periodic_x"])
    nodes = pr["nodes"]
    if periodic:
        x_lo, x_hi = 0.0, float(pr["length_x"])
        n = x_hi / hc
        if abs(n - round(n)) > 1e-6 * max(1.0, n):
            hc = x_hi / max(1, round(n))
    else:
        x_lo, x_hi = pr["origin"][0] + h, pr["origin"][0] + (nodes[0] - 2) * h
    y_lo = min(0.0, float(np.min(x[1])) if x.shape[1] else 0.0)
    y_hi = pr["origin"][1] + (nodes[1] - 1) * h
    g2 = make_conc_grid(x_lo, x_hi, y_lo, y_hi, hc, periodic)
    cg = np.zeros(1, dtype=CONC)
    cg["hc"] = g2.hc
    if x.shape[0] == 3:
        z_lo = pr["origin"][2] + h if pr["zlo_kind"] == 0 else pr["zlo"]
        z_hi = pr["origin"][2] + (nodes[2] - 2) * h if pr["zhi_kind"] == 0 else pr["zhi"]
        ncz = int(np.ceil((z_hi - z_lo) / g2.hc - 1e-9)) + 2
        cg["origin"][0] = (g2.x0, g2.y0, z_lo - g2.hc)
        cg["cells"][0] = (g2.ncx, g2.ncy, ncz)
    else:
        cg["origin"][0] = (g2.x0, g2.y0, 0.0)
        cg["cells"][0] = (g2.ncx, g2.ncy, 1)
    cg["periodic_x"] = g2.periodic_x
    sp = pack_params(cfg, (pr["gravity"][0], pr["gravity"][1]))
    # z-faces take the x-face law (normal 0) with a zero gravity component along them
    sp_z = pack_params(cfg, (0.0, 0.0))
    cells = tuple(int(c) for c in cg["cells"][0])
    return Segregation(grid=cg, prm=sp, prm_z=sp_z, work=np.zeros((nwork, *cells)),
                       corner_cells=np.zeros((8, 3), dtype=np.int64),
                       corner_weights=np.zeros(8))  # fmt: skip


def _points(
    x: np.ndarray,
    v: np.ndarray,
    mass: np.ndarray,
    vol0: np.ndarray,
    J: np.ndarray,
    eps: np.ndarray,
    phi0: float,
    transfer: str,
) -> Points:
    dim, n = x.shape
    ne = eps.shape[0]
    return Points(
        x=np.ascontiguousarray(x), v=v, C=np.zeros((dim * dim, n)), mass=mass, vol0=vol0,
        J=np.ascontiguousarray(J, dtype=np.float64), eps=eps, sig=np.zeros((ne, n)),
        phi=np.full(n, phi0), gf=np.zeros(n), diag=np.zeros((6, n)), s_int=np.zeros(n),
        g_int=np.zeros(n),
        # 8-bit flags and 32-bit slab and point indices: bytes per particle-step
        lg=np.zeros((dim * dim, n)), flags=np.zeros(n, dtype=np.int8),
        cursor=np.zeros(n, dtype=np.int32), x_old=np.zeros((dim, n if transfer == "flip" else 0)),
    )  # fmt: skip


def _engine_strain(cfg: Config, mp: np.ndarray, p_yy: np.ndarray, dim: int):
    """The geostatic elastic strain of the 2-D builders, in the engine's order, and J."""
    eps4, J = _initial_strain(cfg, mp, p_yy)  # (xx, yy, xy, zz) of the 2-D builders
    n = p_yy.shape[0]
    eps = np.zeros((4 if dim == 2 else 6, n))
    eps[0], eps[1], eps[2], eps[3] = eps4[0], eps4[1], eps4[3], eps4[2]
    if dim == 3 and mp[M_KIND] != 0 and cfg.material.initial_state == "isotropic":
        eps[2] = eps4[3]
    return eps, J


def build_column(cfg: Config, threads: int = 1) -> EngineState:
    """The column model of a chute configuration (``scenario.solver = "column"``, 2-D;
    docs/column.md): N = round(H n_ppc/h) two-node elements of the MPM's point spacing over the
    depth H, node 0 on the base y = 0 and the top node the free surface; the geostatic state of
    the MPM builder; the grid one node wide and periodic in x (the fluidity's), of the column's
    width l_x = h; the concentration grid one cell of h_c wide. ``prm.cfl`` holds the column's
    Courant number (``time.column_courant``), the material record the bulk-viscosity floor
    ``COLUMN_BULK_VISCOSITY``."""
    from ..column import COLUMN_BULK_VISCOSITY, column_elements
    from ..materials.params import M_ZETA
    from ..segregation import conc_cell_size, make_conc_grid, pack_params
    from .codegen import for_material, kernels

    g = cfg.geometry
    h = cfg.grid.cell_size
    y_nodes, yc = column_elements(cfg)
    ne = yc.size
    dy = g.depth / ne
    ny = _ny(g.depth * (1 + g.headroom), h)
    prm = _params(cfg, 2, (0.0, -GHOST * h, 0.0), (1, ny, 1), True)
    _sidewall_force(cfg, prm)
    lx = float(prm["length_x"][0])  # = h: the column's width in x, the grid's one periodic cell
    mp = pack_material(cfg)
    mp[M_ZETA] = max(mp[M_ZETA], COLUMN_BULK_VISCOSITY)
    rho = cfg.material.solid_fraction * cfg.material.grain_density
    p_yy = rho * (-prm["gravity"][0, 1]) * (g.depth - yc)
    eps, J = _engine_strain(cfg, mp, p_yy, 2)
    vol0 = np.full(ne, dy * lx) / J
    mass = rho * vol0
    hc = conc_cell_size(cfg)
    x = np.stack([np.full(ne, 0.5 * hc), yc])
    pts = _points(x, np.zeros((2, ne)), mass, vol0, J, eps, cfg.mixture.phi_small_initial, "apic")
    nodes = np.zeros((COL_ROWS, ne + 1))
    nodes[COL_Y] = y_nodes
    nodes[COL_M, :-1] += 0.5 * mass
    nodes[COL_M, 1:] += 0.5 * mass
    prm["c_floor"] = wave_speed_floor(cfg, mp, float(np.max(p_yy)))
    prm["cfl"] = cfg.time.column_courant
    k = kernels(2)
    nonlocal_ = mp[M_KIND] == KIND_FEI2016_NGF
    grid = Grid(
        nodes=np.zeros((1, 1, 1, k.NF)), gv=np.zeros((1, 1, 1, k.NV)),
        slab_start=np.zeros(2, dtype=np.int64), order=np.zeros(ne, dtype=np.int32),
        bounds=np.zeros(max(1, threads) + 1, dtype=np.int64),
        fw=np.zeros((k.NW, *((1, ny, 1) if nonlocal_ else (1, 1, 1)))),
    )  # fmt: skip
    # the concentration grid: one periodic cell of h_c in x (the elements its points)
    g2 = make_conc_grid(0.0, hc, 0.0, float(prm["origin"][0, 1] + (ny - 1) * h), hc, True)
    cg = np.zeros(1, dtype=CONC)
    cg["hc"] = g2.hc
    cg["origin"][0] = (g2.x0, g2.y0, 0.0)
    cg["cells"][0] = (g2.ncx, g2.ncy, 1)
    cg["periodic_x"] = g2.periodic_x
    seg = Segregation(grid=cg, prm=pack_params(cfg, (prm["gravity"][0, 0], prm["gravity"][0, 1])),
                      prm_z=pack_params(cfg, (0.0, 0.0)), work=np.zeros((k.N_CWORK, g2.ncx, g2.ncy, 1)),
                      corner_cells=np.zeros((8, 3), dtype=np.int64), corner_weights=np.zeros(8))  # fmt: skip
    clock = np.zeros(1, dtype=CLOCK)
    st = EngineState(dim=2, points=pts, grid=grid, prm=prm, mp=mp, clock=clock, seg=seg,
                     nodes=nodes, seg_points=pts._replace(vol0=vol0 * (hc / lx)))  # fmt: skip
    for_material(2, st.mat).prime(pts, st.mat)
    prime_clock(st)
    return st


def prime_clock(st: EngineState) -> None:
    """The first step's time-step bound from the primed state: the largest signal speed
    c + |v| and viscosity ν of the points (the loop then keeps them from each step)."""
    d = st.points.diag
    st.clock["smax"] = float(np.max(d[4])) if d.shape[1] else 0.0
    st.clock["numax"] = float(np.max(d[5])) if d.shape[1] else 0.0


def build(cfg: Config, dim: int, threads: int = 1) -> EngineState:
    """The initial state of ``cfg`` in ``dim`` dimensions (geostatic, at rest)."""
    if cfg.scenario.solver == "column":
        if dim != 2:
            raise ValueError("scenario.solver = 'column' is a 2-D model (geometry.dimension = 2)")
        return build_column(cfg, threads)
    kind = cfg.scenario.kind
    if kind not in BUILDERS:
        raise ValueError(f"scenario.kind = {kind!r} is not available in the generic engine")
    x, vol, prm = BUILDERS[kind](cfg, dim)
    n = x.shape[1]
    mp = pack_material(cfg)
    rho = cfg.material.solid_fraction * cfg.material.grain_density
    if kind in ("chute", "collapse"):  # geostatic
        top = cfg.geometry.depth if kind == "chute" else cfg.geometry.column_height
        p_yy = rho * (-prm["gravity"][0, 1]) * (top - x[1])
    else:  # the test bodies start stress-free
        p_yy = np.zeros(n)
    eps, J = _engine_strain(cfg, mp, p_yy, dim)
    vol0 = np.full(n, vol) / J
    mass = rho * vol0
    prm["c_floor"] = wave_speed_floor(cfg, mp, float(np.max(p_yy)) if n else 0.0)
    pts = _points(x, initial_velocity(cfg, x), mass, vol0, J, eps, cfg.mixture.phi_small_initial,
                  cfg.grid.transfer)  # fmt: skip
    nodes = tuple(int(v) for v in prm["nodes"][0])
    from .codegen import for_material, kernels

    k = kernels(dim)
    nonlocal_ = mp[M_KIND] == KIND_FEI2016_NGF
    nslabs = max(1, (nodes[1] + k.SLAB - 1) // k.SLAB)
    grid = Grid(
        nodes=np.zeros((*nodes, k.NF)), gv=np.zeros((*nodes, k.NV)),
        slab_start=np.zeros(nslabs + 1, dtype=np.int64), order=np.zeros(n, dtype=np.int32),
        bounds=np.zeros(max(1, threads) + 1, dtype=np.int64),
        fw=np.zeros((k.NW, *(nodes if nonlocal_ or prm["dilatation"][0] else (1, 1, 1)))),
    )  # fmt: skip
    clock = np.zeros(1, dtype=CLOCK)
    seg = segregation_grid(cfg, prm, x, k.N_CWORK)
    st = EngineState(dim=dim, points=pts, grid=grid, prm=prm, mp=mp, clock=clock, seg=seg)
    for_material(dim, st.mat).prime(pts, st.mat)
    prime_clock(st)
    return st
