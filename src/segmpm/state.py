"""The simulation state: material points (struct of arrays), grid work arrays, scalar state.

Shapes (N material points, grid N_x × N_y nodes):

========== ========= ===============================================================
name       shape     meaning (paper symbol)
========== ========= ===============================================================
x          (2, N)    position (x downslope, y normal to the base), m
v          (2, N)    velocity, m/s
C          (4, N)    APIC affine matrix (C00, C01, C10, C11), 1/s
mass       (N,)      mass per metre of depth m_p, kg/m (constant)
vol0       (N,)      stress-free reference volume V⁰_p = m_p/(f ρ_s), m²
J          (N,)      volume ratio det F relative to V⁰ (I₁ = −ln J for fei2016)
eps        (4, N)    elastic strain ε^e (xx, yy, xy, zz), tension positive
sig        (4, N)    Cauchy stress σ (xx, yy, xy, zz), Pa
phi        (N,)      small-grain concentration φ_s
gf         (N,)      granular fluidity g (nonlocal rheology; 0 otherwise), 1/s
diag       (6, N)    p_e (Pa), γ̇ (1/s), I, S (Pa), c + |v| (m/s), ν (m²/s)
s_int      (N,)      ∫ S dt over the current segregation subcycle, Pa s
g_int      (N,)      ∫ γ̇ dt over the current segregation subcycle
sc         (S_NSLOTS) scalar state: time, steps, Δt, … (mpm.params S_*)
nodes      (4, N+1)  column model only (``scenario.solver = "column"``): the nodes of the
                     1-D elements, rows ``column.COL_*`` (y, u, v, lumped mass); the points
                     are then the elements
========== ========= ===============================================================
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .mpm.fluidity import allocate as fluidity_work
from .mpm.params import G_NX, G_NY, S_NSLOTS
from .mpm.transfer import N_FIELDS, STRIP, V_LANES

#: arrays that define the physical state (saved in checkpoints)
STATE_ARRAYS = (
    "x", "v", "C", "mass", "vol0", "J", "eps", "sig", "phi", "gf", "diag", "s_int", "g_int",
)  # fmt: skip

D_PRESSURE, D_SHEAR_RATE, D_INERTIAL, D_DRIVER, D_SPEED, D_NU = range(6)


@dataclass
class State:
    """Material points, scalar state and the preallocated work arrays of the compiled loop."""

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
    sc: np.ndarray
    gp: np.ndarray
    mp: np.ndarray
    work: dict[str, np.ndarray] = field(default_factory=dict)
    #: segregation: parameter record (segregation.closures ``P_*``), concentration grid, scratch
    seg_prm: np.ndarray | None = None
    cg: Any = None
    seg_work: tuple = ()
    #: the column model's nodes (None for the MPM; saved in checkpoints when present)
    nodes: np.ndarray | None = None

    @property
    def n(self) -> int:
        """Number of material points."""
        return int(self.mass.shape[0])

    @classmethod
    def from_points(
        cls,
        x: np.ndarray,
        v: np.ndarray,
        mass: np.ndarray,
        vol0: np.ndarray,
        J: np.ndarray,
        eps: np.ndarray,
        phi: np.ndarray,
        gp: np.ndarray,
        mp: np.ndarray,
    ) -> State:
        """Build a state from point data (shapes as in the module docstring)."""
        n = mass.shape[0]
        st = cls(
            x=np.ascontiguousarray(x, dtype=np.float64),
            v=np.ascontiguousarray(v, dtype=np.float64),
            C=np.zeros((4, n)),
            mass=np.ascontiguousarray(mass, dtype=np.float64),
            vol0=np.ascontiguousarray(vol0, dtype=np.float64),
            J=np.ascontiguousarray(J, dtype=np.float64),
            eps=np.ascontiguousarray(eps, dtype=np.float64),
            sig=np.zeros((4, n)),
            phi=np.ascontiguousarray(phi, dtype=np.float64),
            gf=np.zeros(n),
            diag=np.zeros((6, n)),
            s_int=np.zeros(n),
            g_int=np.zeros(n),
            sc=np.zeros(S_NSLOTS),
            gp=gp,
            mp=mp,
        )
        st.allocate_work()
        return st

    def allocate_work(self) -> None:
        """(Re)allocate the grid and sorting work arrays for this state's grid."""
        nx, ny, n = int(self.gp[G_NX]), int(self.gp[G_NY]), self.n
        nstrips = ny // STRIP + 2
        self.work = {
            "grid": np.zeros((nx, ny, N_FIELDS)),
            "gv": np.zeros((nx, ny, V_LANES)),
            "strip_start": np.zeros(nstrips + 1, dtype=np.int64),
            # 32-bit point indices and 8-bit flags: bytes per particle-step (docs/performance.md)
            "cursor": np.zeros(n, dtype=np.int32),
            "order": np.zeros(n, dtype=np.int32),
            "flags": np.zeros(n, dtype=np.int8),
            "x_old": np.zeros((2, n)),
            "lg": np.zeros((4, n)),
            # nodal fields of the fluidity update (mpm.fluidity)
            "fw": fluidity_work(nx, ny),
        }
        if self.cg is not None:
            from .segregation import allocate_work

            self.seg_work = allocate_work(self.cg)

    def arrays(self) -> dict[str, np.ndarray]:
        """The physical state arrays (no work arrays; the column's nodes when present)."""
        out = {k: getattr(self, k) for k in (*STATE_ARRAYS, "sc")}
        if self.nodes is not None:
            out["nodes"] = self.nodes
        return out

    def copy(self) -> State:
        """Deep copy (work arrays reallocated)."""
        st = State(
            **{k: v.copy() for k, v in self.arrays().items()}, gp=self.gp.copy(), mp=self.mp.copy()
        )
        st.allocate_work()
        return st
