"""Scenario builders (docs/model.md §1 "Initial state" and §2 "Boundaries" for the chute).

Material points sit on a regular lattice, ``particles_per_cell`` per cell and direction; the
lattice spacing is stretched slightly so that the body fills its nominal extent exactly. Every
builder returns a :class:`~segmpm.state.State` whose grid record (``gp``) carries the boundaries:
the 2-D initial state in the layout of the NumPy reference step (segmpm.mpm.reference), which
the tests compare the engine with. The engine builds its own records (segmpm.engine.setup) and
shares the initial strain, gravity and wave-speed floor written here.
"""

from __future__ import annotations

import math

import numpy as np

from ..config import Config
from ..materials import KIND_LINEAR_ELASTIC, pack_material
from ..materials.fei2016 import oedometric_strain
from ..materials.params import M_A, M_C, M_KIND, M_LAMBDA, M_MU
from ..mpm.params import (
    BC_CODES,
    BC_NOSLIP,
    BC_OPEN,
    G_BASE_KIND,
    G_BASE_MU,
    G_BASE_Y,
    G_CFL,
    G_CFLOOR,
    G_DTMAX,
    G_DTMIN,
    G_FLIP,
    G_GX,
    G_GY,
    G_H,
    G_IMAGES,
    G_LX,
    G_NSLOTS,
    G_NX,
    G_NY,
    G_PERIODIC,
    G_RAMP,
    G_SIDEWALL,
    G_SW_SLOW,
    G_SW_SPEED,
    G_TRANSFER,
    G_VISC,
    G_WALL_MU,
    G_X0,
    G_XHI,
    G_XHI_KIND,
    G_XLO,
    G_XLO_KIND,
    G_Y0,
    TRANSFER_AFLIP,
    TRANSFER_APIC,
    TRANSFER_FLIP,
)
from ..state import State

#: ghost node rows kept below the lowest point / beside non-periodic walls
GHOST = 3


def gravity_vector(cfg: Config) -> tuple[float, float]:
    """g in the slope frame: (g sin θ, −g cos θ) (x downslope, y normal to the base)."""
    th = math.radians(cfg.geometry.slope_deg)
    return cfg.time.gravity * math.sin(th), -cfg.time.gravity * math.cos(th)


def lattice(lo: tuple[float, ...], hi: tuple[float, ...], spacing: float | tuple[float, ...]):
    """Cell-centred lattice filling the box [lo, hi] (2 or 3 axes) at about ``spacing`` (one
    value, or one per axis); returns (x (D, N), volume per point). Points are ordered with y
    slowest, so that they come sorted by height. The NumPy reference builders below and the
    engine's set-up (``engine.setup``) both seed their points with it."""
    axes = []
    vol = 1.0
    spacings = (spacing,) * len(lo) if isinstance(spacing, float | int) else spacing
    for a, b, ds in zip(lo, hi, spacings, strict=True):
        n = max(1, round((b - a) / ds))
        s = (b - a) / n
        axes.append(a + (np.arange(n) + 0.5) * s)
        vol *= s
    if len(axes) == 2:
        Y, X = np.meshgrid(axes[1], axes[0], indexing="ij")
        return np.stack([X.ravel(), Y.ravel()]), vol
    Y, X, Z = np.meshgrid(axes[1], axes[0], axes[2], indexing="ij")
    return np.stack([X.ravel(), Y.ravel(), Z.ravel()]), vol


def grid_record(
    cfg: Config,
    *,
    x0: float,
    nx: int,
    y0: float,
    ny: int,
    periodic: bool,
    base: str,
    xlo: str = "open",
    xhi: str = "open",
    x_hi_wall: float = 0.0,
    sidewall: bool = True,
    gravity: bool = True,
) -> np.ndarray:
    """The grid/boundary/time-step record ``gp`` (mpm.params ``G_*``)."""
    h = cfg.grid.cell_size
    b = cfg.boundary
    gp = np.zeros(G_NSLOTS)
    gp[G_X0], gp[G_Y0], gp[G_H] = x0, y0, h
    gp[G_NX], gp[G_NY] = nx, ny
    gp[G_PERIODIC] = 1.0 if periodic else 0.0
    gp[G_LX] = nx * h if periodic else 0.0
    gp[G_BASE_KIND] = BC_CODES[base]
    gp[G_BASE_Y] = 0.0
    gp[G_BASE_MU] = b.base_friction
    gp[G_XLO_KIND] = BC_CODES[xlo]
    gp[G_XLO] = 0.0
    gp[G_XHI_KIND] = BC_CODES[xhi]
    gp[G_XHI] = x_hi_wall
    gp[G_WALL_MU] = b.wall_friction
    gx, gy = gravity_vector(cfg) if gravity else (0.0, 0.0)
    gp[G_GX], gp[G_GY] = gx, gy
    if sidewall and (b.sidewall_friction > 0 or b.sidewall_slip_speed > 0):
        k = 2.0 * b.wall_normal_stress_ratio / cfg.geometry.width
        gp[G_SIDEWALL] = k * b.sidewall_friction
        if b.sidewall_slip_speed > 0:
            gp[G_SW_SLOW] = k * b.sidewall_friction_slow
            gp[G_SW_SPEED] = b.sidewall_slip_speed
    gp[G_RAMP] = b.ramp_time
    gp[G_CFL] = cfg.time.cfl
    gp[G_VISC] = cfg.time.viscous_number
    gp[G_DTMAX] = cfg.time.dt_max
    gp[G_DTMIN] = cfg.time.dt_min
    gp[G_TRANSFER] = {"apic": TRANSFER_APIC, "flip": TRANSFER_FLIP, "aflip": TRANSFER_AFLIP}[
        cfg.grid.transfer
    ]
    gp[G_FLIP] = cfg.grid.flip_fraction
    gp[G_IMAGES] = 1.0 if b.wall_images else 0.0
    return gp


def _initial_strain(cfg: Config, mp: np.ndarray, p_yy: np.ndarray):
    """Elastic strain (4, N) and J carrying σ_yy = −p_yy: oedometric ("geostatic") or isotropic."""
    n = p_yy.shape[0]
    eps = np.zeros((4, n))
    J = np.ones(n)
    if cfg.material.initial_state == "stress_free":
        return eps, J
    if cfg.material.initial_state == "isotropic":
        if mp[M_KIND] != KIND_LINEAR_ELASTIC:
            I1 = (np.maximum(p_yy, 0.0) / (2.5 * mp[M_A])) ** (2.0 / 3.0)  # p = 2.5 A I₁^{3/2}
        else:
            I1 = np.maximum(p_yy, 0.0) / (mp[M_LAMBDA] + 2.0 * mp[M_MU] / 3.0)  # p = K I₁
        eps[0] = eps[1] = eps[3] = -I1 / 3.0
        return eps, np.exp(-I1) if mp[M_KIND] != KIND_LINEAR_ELASTIC else J
    if mp[M_KIND] != KIND_LINEAR_ELASTIC:  # the Jiang–Liu energy (local or nonlocal flow rule)
        e = oedometric_strain(p_yy, mp[M_A], mp[M_C])
        J = np.exp(-e)  # I₁ = −ln J = e
    else:
        e = np.maximum(p_yy, 0.0) / (mp[M_LAMBDA] + 2.0 * mp[M_MU])
    eps[1] = -e
    return eps, J


def _points_state(cfg, x, area, gp, mp, p_yy, velocity=None) -> State:
    n = x.shape[1]
    eps, J = _initial_strain(cfg, mp, p_yy)
    rho_ref = cfg.material.solid_fraction * cfg.material.grain_density
    vol0 = np.full(n, area) / J  # stress-free reference volume
    mass = rho_ref * vol0
    v = np.zeros((2, n)) if velocity is None else velocity
    phi = np.full(n, cfg.mixture.phi_small_initial)
    gp[G_CFLOOR] = wave_speed_floor(cfg, mp, float(np.max(p_yy)) if n else 0.0)
    return State.from_points(x, v, mass, vol0, J, eps, phi, gp, mp)


def wave_speed_floor(cfg: Config, mp: np.ndarray, p_ref: float) -> float:
    """Elastic wave speed of the material loaded to ``p_ref`` (the largest initial load), m/s.

    The time step never uses a smaller wave speed (``G_CFLOOR``): a gas (stress-free) region has
    c = 0, and re-contact makes it stiff within one step. Fei model: the safe bound
    √((3.75 A + 2 C) √I₁/ρ) at the oedometric I₁ of p_ref (docs/model.md §1); linear elastic: the
    P-wave speed.
    """
    rho = cfg.material.solid_fraction * cfg.material.grain_density
    if mp[M_KIND] != KIND_LINEAR_ELASTIC:
        I1 = float(oedometric_strain(np.array([p_ref]), mp[M_A], mp[M_C])[0])
        return math.sqrt((3.75 * mp[M_A] + 2.0 * mp[M_C]) * math.sqrt(I1) / rho)
    return math.sqrt((mp[M_LAMBDA] + 2.0 * mp[M_MU]) / rho)


def _ny(top: float, h: float) -> int:
    return int(math.ceil(top / h)) + 2 * GHOST + 1


def build_chute(cfg: Config) -> State:
    """Periodic layer of depth H on a slope θ with a no-slip base at y = 0 (docs/validation.md)."""
    g = cfg.geometry
    h = cfg.grid.cell_size
    nx = round(g.length / h)
    spacing = cfg.grid.point_spacing(2)
    x, area = lattice((0.0, 0.0), (nx * h, g.depth), spacing)
    gp = grid_record(
        cfg, x0=0.0, nx=nx, y0=-GHOST * h, ny=_ny(g.depth * (1 + g.headroom), h),
        periodic=True, base=cfg.boundary.base,
    )  # fmt: skip
    mp = pack_material(cfg)
    rho = cfg.material.solid_fraction * cfg.material.grain_density
    p_yy = rho * (-gp[G_GY]) * (g.depth - x[1])
    return _points_state(cfg, x, area, gp, mp, p_yy)


def build_box(cfg: Config) -> State:
    """Periodic layer of depth H floating in the middle of the grid (no base): free fall and
    momentum tests. It moves with ``scenario.velocity`` along x; stress-free."""
    g = cfg.geometry
    h = cfg.grid.cell_size
    nx = round(g.length / h)
    spacing = cfg.grid.point_spacing(2)
    bottom = g.headroom * g.depth
    x, area = lattice((0.0, bottom), (nx * h, bottom + g.depth), spacing)
    gp = grid_record(
        cfg, x0=0.0, nx=nx, y0=-GHOST * h, ny=_ny(g.depth * (1 + 2 * g.headroom), h),
        periodic=True, base="open", sidewall=False,
    )  # fmt: skip
    mp = pack_material(cfg)
    vel = np.zeros_like(x)
    vel[0] = cfg.scenario.velocity
    st = _points_state(cfg, x, area, gp, mp, np.zeros(x.shape[1]), velocity=vel)
    st.C[:] = 0.0
    return st


def build_bar(cfg: Config) -> State:
    """Elastic bar of length L along x, fixed at x = 0, free at x = L (docs/model.md §3).

    Initial velocity v₀ sin(πx/2L) along x (``scenario.velocity``); no gravity, no sidewall force.
    """
    g = cfg.geometry
    h = cfg.grid.cell_size
    spacing = cfg.grid.point_spacing(2)
    L = g.length
    x, area = lattice((0.0, 0.0), (L, g.depth), spacing)
    nxc = int(math.ceil(L * (1 + g.headroom) / h))
    gp = grid_record(
        cfg, x0=-GHOST * h, nx=nxc + 2 * GHOST + 1, y0=-GHOST * h, ny=_ny(g.depth, h),
        periodic=False, base="open", xlo="noslip", xhi="open", sidewall=False, gravity=False,
    )  # fmt: skip
    mp = pack_material(cfg)
    vel = np.zeros_like(x)
    vel[0] = cfg.scenario.velocity * np.sin(np.pi * x[0] / (2 * L))
    return _points_state(cfg, x, area, gp, mp, np.zeros(x.shape[1]), velocity=vel)


def build_collapse(cfg: Config) -> State:
    """Column L₀ × H₀ against a wall at x = 0 on a rough base, domain [0, length].

    Runout laws: docs/validation.md §2.
    """
    g = cfg.geometry
    h = cfg.grid.cell_size
    spacing = cfg.grid.point_spacing(2)
    x, area = lattice((0.0, 0.0), (g.column_width, g.column_height), spacing)
    nxc = int(math.ceil(g.length / h))
    gp = grid_record(
        cfg, x0=-GHOST * h, nx=nxc + 2 * GHOST + 1, y0=-GHOST * h,
        ny=_ny(g.column_height * (1 + g.headroom), h), periodic=False,
        base=cfg.boundary.base, xlo=cfg.boundary.walls, xhi=cfg.boundary.walls,
        x_hi_wall=nxc * h, sidewall=True,
    )  # fmt: skip
    mp = pack_material(cfg)
    rho = cfg.material.solid_fraction * cfg.material.grain_density
    p_yy = rho * (-gp[G_GY]) * (g.column_height - x[1])
    return _points_state(cfg, x, area, gp, mp, p_yy)


__all__ = ["BC_NOSLIP", "BC_OPEN", "build_bar", "build_box", "build_chute", "build_collapse"]


def attach_segregation(cfg: Config, st: State) -> None:
    """The extra Eulerian concentration grid over the whole MPM grid, and its parameters.

    The grid spans the MPM grid (periodic with the same period, or between the outer nodes), from
    the base (y = 0) to the top node, with cells of ``segregation.cell_size`` (default h/2).
    """
    from ..segregation import conc_cell_size, make_conc_grid, pack_params

    gp = st.gp
    h = gp[G_H]
    hc = conc_cell_size(cfg)
    periodic = gp[G_PERIODIC] != 0.0
    if periodic:
        x_lo, x_hi = 0.0, gp[G_LX]
        # the periodic length must hold a whole number of concentration cells
        n = x_hi / hc
        if abs(n - round(n)) > 1e-6 * max(1.0, n):
            hc = x_hi / max(1, round(n))
    else:
        x_lo, x_hi = gp[G_X0] + h, gp[G_X0] + (gp[G_NX] - 2) * h
    y_lo = min(0.0, float(np.min(st.x[1])) if st.n else 0.0)
    y_hi = gp[G_Y0] + (gp[G_NY] - 1) * h
    st.cg = make_conc_grid(x_lo, x_hi, y_lo, y_hi, hc, periodic)
    st.seg_prm = pack_params(cfg, (gp[G_GX], gp[G_GY]))
