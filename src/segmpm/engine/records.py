"""Named records of the dimension-generic engine (docs/architecture.md).

Everything the compiled step reads travels in one of these, by name:

* :data:`PARAMS` – grid, boundary planes, gravity and time-step control (a NumPy structured
  scalar; read-only in the loop);
* :data:`CLOCK` – the scalar state carried between calls (time, step count, last Δt, …); a
  one-element structured array, written by the loop;
* :data:`MATERIAL` – the constitutive parameters: a *named view* of the record
  :func:`segmpm.materials.params.pack_material` builds, so that the two can never disagree;
* :class:`Points` – the material points (struct of arrays, shapes below);
* :class:`Grid` – the nodal arrays and the P2G sort's work arrays.

The arrays of :class:`Points` (N points, D = 2 or 3; the symmetric tensors stored as
``xx, yy, zz, xy`` and, in 3-D, ``xz, yz``: index constants ``XX … YZ``):

========= ========== ================================================================
name      shape      meaning (paper symbol)
========= ========== ================================================================
x         (D, N)     position, m (x downslope, y normal to the base, z across)
v         (D, N)     velocity, m/s
C         (D·D, N)   APIC affine matrix, row-major (C_xx, C_xy, …), 1/s
mass      (N,)       mass m_p, kg (kg per metre of depth in 2-D)
vol0      (N,)       stress-free volume V⁰_p = m_p/(f ρ_s)
J         (N,)       volume ratio det F (I₁ = −ln J)
eps       (NE, N)    elastic strain ε^e, tension positive (NE = 4 in 2-D, 6 in 3-D)
sig       (NE, N)    Cauchy stress σ, Pa
phi       (N,)       small-grain concentration φ_s
gf        (N,)       granular fluidity g of the nonlocal rheology, 1/s (0 otherwise)
diag      (6, N)     p_e, γ̇, I, S, c + |v|, ν (rows ``D_*``)
s_int     (N,)       ∫ S dt over the current segregation subcycle
g_int     (N,)       ∫ γ̇ dt over the current segregation subcycle
lg        (D·D, N)   velocity gradient L of the last G2P (work)
flags     (N,)       per-point status of the last G2P (work)
cursor    (N,)       P2G slab of each point (work)
x_old     (D, N)     positions before the step's G2P, for the MUSL remap (work; (D, 0)
                     unless ``grid.transfer = "flip"``)
========= ========== ================================================================
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..materials import params as _mparams

#: symmetric-tensor components in the engine's storage order
XX, YY, ZZ, XY, XZ, YZ = range(6)

#: rows of the points' ``diag``: p_e (Pa), γ̇ (1/s), I, S (Pa), c + |v| (m/s), ν (m²/s)
D_PRESSURE, D_SHEAR_RATE, D_INERTIAL, D_DRIVER, D_SPEED, D_NU = range(6)

#: rows of the column model's node array (COL_ROWS, N + 1) (``scenario.solver = "column"``):
#: position y (m), velocity u (downslope) and v (normal), lumped mass per metre of z (kg/m)
COL_Y, COL_U, COL_V, COL_M, COL_ROWS = range(5)

#: boundary-plane kinds (``PARAMS`` ``*_kind``): the 2-D engine's codes plus a symmetry plane
#: (mirror: no normal velocity, free tangential, never separates)
from ..mpm.params import BC_CODES, BC_FRICTION, BC_NOSLIP, BC_OPEN, BC_SLIP  # noqa: E402

BC_SYMMETRY = 4
PLANE_CODES = {**BC_CODES, "symmetry": BC_SYMMETRY}

#: grid, boundaries, gravity, time-step control
PARAMS = np.dtype(
    [
        ("dim", "i8"),  # 2 or 3
        ("h", "f8"),  # cell size, m
        ("origin", "f8", (3,)),  # position of node (0, 0, 0), m
        ("nodes", "i8", (3,)),  # nodes per axis (1 along z in 2-D)
        ("periodic_x", "i8"),  # 1: x periodic with length length_x
        ("length_x", "f8"),
        ("gravity", "f8", (3,)),  # slope-frame gravity, m/s²
        ("ramp", "f8"),  # ramp time of tangential gravity and sidewall friction, s
        ("transfer", "i8"),  # 0 APIC, 1 MUSL FLIP/PIC, 2 AFLIP (segmpm.mpm.params TRANSFER_*)
        ("flip", "f8"),  # FLIP fraction α of AFLIP and FLIP
        ("cfl", "f8"),
        ("visc", "f8"),  # Δt ≤ visc h²/(2 ν_max)
        ("dt_max", "f8"),
        ("dt_min", "f8"),
        ("c_floor", "f8"),  # floor on the wave speed of the time step, m/s
        ("images", "i8"),  # 1: image nodes behind walls on node planes (boundary.wall_images)
        # 1: the volumetric rate tr L of each point replaced by its mass-weighted grid average
        # (grid.volumetric_smoothing; docs/model.md, "Volumetric smoothing")
        ("dilatation", "i8"),
        # 2-D only: the sidewall Coulomb body force 2 μ_w K_w / W (and its slow value, u_w)
        ("sidewall", "f8"),
        ("sidewall_slow", "f8"),
        ("sidewall_speed", "f8"),
        # boundary planes: kind (BC_*), position, Coulomb μ (friction kind)
        ("base_kind", "i8"),  # y = base_y (nodes at and below)
        ("base_y", "f8"),
        ("base_mu", "f8"),
        ("xlo_kind", "i8"),  # x = xlo (non-periodic x only)
        ("xlo", "f8"),
        ("xlo_mu", "f8"),
        ("xhi_kind", "i8"),
        ("xhi", "f8"),
        ("xhi_mu", "f8"),
        ("zlo_kind", "i8"),  # z = zlo, 3-D only (a resolved sidewall or a symmetry plane)
        ("zlo", "f8"),
        ("zlo_mu", "f8"),
        ("zhi_kind", "i8"),
        ("zhi", "f8"),
        ("zhi_mu", "f8"),
        # 3-D resolved sidewalls: μ(u) = μ₀ + (μ − μ₀) u/(u + u_w) of the sliding speed u
        # (u_w = ``wall_speed`` > 0; 0: the constant Coulomb μ of zlo_mu, zhi_mu)
        ("wall_mu0", "f8"),
        ("wall_speed", "f8"),
    ],
    align=True,
)

#: the extra Eulerian concentration grid (cells of side h_c, centres at origin + (i + ½) h_c)
CONC = np.dtype(
    [
        ("origin", "f8", (3,)),  # corner of cell (0, 0, 0), m
        ("hc", "f8"),  # cell size h_c, m
        ("cells", "i8", (3,)),  # cells per axis (1 along z in 2-D)
        ("periodic_x", "i8"),
    ],
    align=True,
)


class Segregation(NamedTuple):
    """The segregation sub-step's grid, parameters (segregation.closures ``P_*``) and work."""

    grid: np.ndarray  # CONC, one element
    prm: np.ndarray  # the closure's parameter vector
    prm_z: np.ndarray  # the same with no gravity in the face law: the z-faces' (3-D)
    work: np.ndarray  # (N_CWORK, n_x, n_y, n_z) scratch, indices C_* of the kernels
    corner_cells: np.ndarray  # (8, 3) int64 scratch: a point's cells
    corner_weights: np.ndarray  # (8,) scratch: their weights


#: the scalar state carried between calls of the time loop
CLOCK = np.dtype(
    [
        ("time", "f8"),  # simulated time t, s
        ("step", "i8"),  # steps taken
        ("dt", "f8"),  # last Δt, s
        ("smax", "f8"),  # max over points of c + |v| after the last step, m/s
        ("numax", "f8"),  # max kinematic viscosity after the last step, m²/s
        ("tseg", "f8"),  # time accumulated towards the next concentration step, s
        ("nseg", "i8"),  # concentration steps taken
        ("tflu", "f8"),  # time accumulated towards the next fluidity update, s
        ("nflu", "i8"),  # fluidity updates taken
    ],
    align=True,
)


def _material_dtype() -> np.dtype:
    names = sorted(
        (v, k[2:].lower())
        for k, v in vars(_mparams).items()
        if k.startswith("M_") and k != "M_NSLOTS" and isinstance(v, int)
    )
    assert [v for v, _ in names] == list(range(_mparams.M_NSLOTS)), "M_* slots must be 0..n-1"
    # ``lambda`` is a Python keyword: the Lamé constant's field is ``lame_lambda``
    return np.dtype([("lame_lambda" if n == "lambda" else n, "f8") for _, n in names])


#: the material record: field ``name`` is slot ``M_NAME`` of pack_material (e.g. ``mu_a``, ``capr``)
MATERIAL = _material_dtype()


def material_record(mp: np.ndarray) -> np.ndarray:
    """The named view of a packed material record: a one-element MATERIAL array sharing its
    memory (compiled kernels take records as one-element arrays)."""
    return np.ascontiguousarray(mp, dtype=np.float64).view(MATERIAL)


class Points(NamedTuple):
    """The material points: struct of arrays (shapes in the module docstring)."""

    x: np.ndarray
    v: np.ndarray
    C: np.ndarray
    mass: np.ndarray
    vol0: np.ndarray
    J: np.ndarray
    eps: np.ndarray
    sig: np.ndarray
    phi: np.ndarray
    gf: np.ndarray
    diag: np.ndarray
    s_int: np.ndarray
    g_int: np.ndarray
    lg: np.ndarray
    flags: np.ndarray
    cursor: np.ndarray
    x_old: np.ndarray


#: arrays of Points that define the physical state (checkpointed); the rest is work
POINT_STATE = (
    "x",
    "v",
    "C",
    "mass",
    "vol0",
    "J",
    "eps",
    "sig",
    "phi",
    "gf",
    "diag",
    "s_int",
    "g_int",
)


class Grid(NamedTuple):
    """Nodal arrays (n_x, n_y, n_z, fields) and the P2G sort's work arrays."""

    nodes: np.ndarray  # P2G sums, fields F_* of the kernels
    gv: np.ndarray  # nodal velocities: new (D lanes) then old (D lanes)
    slab_start: np.ndarray  # (n_slabs + 1,) first sorted point of each slab
    order: np.ndarray  # (N,) points sorted by slab
    bounds: np.ndarray  # (threads + 1,) balanced slab runs of one colour
    fw: np.ndarray  # (NW, n_x, n_y, n_z) the fluidity update's nodal work (nonlocal rheology)


__all__ = [
    "BC_FRICTION", "BC_NOSLIP", "BC_OPEN", "BC_SLIP", "BC_SYMMETRY", "CLOCK", "COL_M",
    "COL_ROWS", "COL_U", "COL_V", "COL_Y", "Grid", "MATERIAL",
    "PARAMS", "PLANE_CODES", "POINT_STATE", "Points", "XX", "XY", "XZ", "YY", "YZ", "ZZ",
    "material_record",
]  # fmt: skip
