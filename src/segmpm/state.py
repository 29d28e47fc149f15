"""The plane-strain state layout of the NumPy references (segmpm.mpm.reference.step_np,
segmpm.column.column_step_np): material points (struct of arrays) and the scalar state. The
engine's own records are segmpm.engine.records; tests translate between the two.

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

from dataclasses import dataclass
from typing import Any

import numpy as np

from .engine.records import D_DRIVER, D_INERTIAL, D_NU, D_PRESSURE, D_SHEAR_RATE, D_SPEED
from .mpm.params import S_NSLOTS

#: arrays that define the physical state (saved in checkpoints)
STATE_ARRAYS = (
    "x", "v", "C", "mass", "vol0", "J", "eps", "sig", "phi", "gf", "diag", "s_int", "g_int",
)  # fmt: skip

#: the rows of ``diag`` (defined with the engine's records)
DIAG_ROWS = (D_PRESSURE, D_SHEAR_RATE, D_INERTIAL, D_DRIVER, D_SPEED, D_NU)


@dataclass
class State:
    """Material points, scalar state and the records of the NumPy reference step."""

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
    #: segregation: parameter record (segregation.closures ``P_*``) and concentration grid
    seg_prm: np.ndarray | None = None
    cg: Any = None
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
        return st

    def arrays(self) -> dict[str, np.ndarray]:
        """The physical state arrays (the column's nodes when present)."""
        out = {k: getattr(self, k) for k in (*STATE_ARRAYS, "sc")}
        if self.nodes is not None:
            out["nodes"] = self.nodes
        return out

    def copy(self) -> State:
        """Deep copy."""
        return State(
            **{k: v.copy() for k, v in self.arrays().items()}, gp=self.gp.copy(), mp=self.mp.copy()
        )
