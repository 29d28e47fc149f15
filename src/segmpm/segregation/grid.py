"""The extra Eulerian concentration grid and the species-transport step (seed Fig. 1 i–k) on it.

``concentration_step`` advances the small-grain concentration φ^s_p of the material points over one
subcycle of length t_int (docs/segregation.md §2):

(i)   MP → grid with tent (bilinear) weights w_cp to the cell centres (Σ_c w_cp = 1), restricted
      to the active cells (raw fill θ_c ≥ θ_min) and renormalised:
      V_c = Σ w V⁰_p, φ_c = Σ w V⁰_p φ_p / V_c, S_c and γ̇_c volume-weighted time averages,
      fill fraction θ_c = V_c / h_c²;
(j)   explicit finite-volume update of φ_c with the closure's face velocity w and diffusivity D
      (closures.py) and the Scharfetter–Gummel (or upwind + central) face flux; faces that touch an
      inactive cell (θ < θ_min) and the domain edges carry no flux; substeps of
      Δt_c = safety · min_c θ_c h_c / Σ_faces max(a_f, b_f) (a cell-wise form of the bound
      θ_min h_c/(2 max|w| + 2D/h_c) of an explicit monotone flux, to which it reduces in 1-D);
(k)   grid → MP incremental, bound-preserving mapping Δφ_p = Σ_c w_cp ω_cp Δφ_c with
      ω_cp = (1 − φ_p)/(1 − φ_c) if Δφ_c > 0, φ_p/φ_c otherwise; this conserves Σ_p V⁰_p φ_p
      and keeps 0 ≤ φ_p ≤ 1.

The closure coefficients (w, D and the face rates a, b) are evaluated once per call from the state
at its start (S, γ̇ time-averaged over the subcycle; d̄ from φ_c) and frozen over the substeps.
The scheme is then monotone for any coefficients, so boundedness holds exactly.
Model, numerics and measured accuracy: docs/segregation.md.

The step is compiled once, in the engine (``engine/kernels.py``, ``concentration_step``, in D
dimensions; the time loop calls it every ``segregation.dt``). This module holds the 2-D grid's
geometry (:class:`ConcGrid`, :func:`make_conc_grid`), the tent weights the engine uses, and
:func:`concentration_step`, which runs the engine's 2-D step on plain arrays: the standalone
interface of docs/segregation.md and of the closed-form tests (tests/test_segregation_*.py).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit


class ConcGrid(NamedTuple):
    """Geometry of the concentration grid (square cells h_c × h_c, centres at x0 + (i + ½) h_c)."""

    x0: float  #: x of the lower-left corner of cell (0, 0), m
    y0: float  #: y of the lower-left corner of cell (0, 0), m
    hc: float  #: cell size h_c, m
    ncx: int  #: cells in x
    ncy: int  #: cells in y
    periodic_x: int  #: 1: periodic in x with period ncx·h_c; 0: closed (zero flux) in x


def make_conc_grid(
    x_lo: float, x_hi: float, y_lo: float, y_hi: float, hc: float, periodic_x: int | bool
) -> ConcGrid:
    """A concentration grid covering [x_lo, x_hi] × [y_lo, y_hi] with cells of size h_c.

    A ghost ring of one cell is added in y and, when not periodic, in x, so every material point
    inside the region has all four tent-weight cells on the grid. When periodic, x_hi − x_lo must
    be a whole number of cells (the period is ncx·h_c and x0 = x_lo).
    """
    if not (hc > 0.0 and math.isfinite(hc)):
        raise ValueError(f"concentration cell size hc = {hc} must be positive and finite")
    if not (x_hi > x_lo and y_hi > y_lo):
        raise ValueError(f"empty region [{x_lo}, {x_hi}] × [{y_lo}, {y_hi}]")
    if periodic_x:
        n = (x_hi - x_lo) / hc
        ncx = round(n)
        if ncx < 1 or abs(n - ncx) > 1e-6 * max(1.0, n):
            raise ValueError(
                f"periodic length {x_hi - x_lo} must be a whole number of cells hc = {hc} "
                f"(got {n:.6g})"
            )
        x0 = float(x_lo)
    else:
        ncx = math.ceil((x_hi - x_lo) / hc - 1e-9) + 2
        x0 = float(x_lo - hc)
    ncy = math.ceil((y_hi - y_lo) / hc - 1e-9) + 2
    y0 = float(y_lo - hc)
    return ConcGrid(x0, y0, float(hc), int(ncx), int(ncy), 1 if periodic_x else 0)


def allocate_work(cg: ConcGrid) -> np.ndarray:
    """The scratch of :func:`concentration_step` for the grid ``cg``, allocated once: the
    engine's concentration work array (its rows ``C_*``), shape (N_CWORK, ncx, ncy, 1)."""
    from ..engine.codegen import kernels

    return np.zeros((kernels(2).N_CWORK, cg.ncx, cg.ncy, 1))


@njit(cache=True, error_model="numpy")
def tent_weights(
    x: float, x0: float, hc: float, n: int, periodic: int
) -> tuple[int, int, float, float]:
    """Linear (tent) weights of position x to the two nearest cell centres x0 + (i + ½) h_c.

    Returns (i0, i1, w0, w1) with w0 + w1 = 1. Periodic: indices wrap. Closed: a position outside
    the span of the centres is clamped to the edge cell (weights still sum to one).
    """
    f = (x - x0) / hc - 0.5
    if not (f == f):  # NaN position: put it in cell 0; the engine's NaN check reports it
        f = 0.0
    fi = math.floor(f)
    t = f - fi
    i0 = int(fi)
    if periodic == 1:
        i0 = i0 % n
        if i0 < 0:
            i0 += n
        i1 = i0 + 1
        if i1 >= n:
            i1 = 0
    else:
        if n < 2:
            return 0, 0, 1.0, 0.0
        if i0 < 0:
            i0 = 0
            t = 0.0
        elif i0 > n - 2:
            i0 = n - 2
            t = 1.0
        i1 = i0 + 1
    return i0, i1, 1.0 - t, t


def _f64(name: str, a: np.ndarray, n: int) -> np.ndarray:
    if not (isinstance(a, np.ndarray) and a.dtype == np.float64 and a.shape == (n,)
            and a.flags.c_contiguous):  # fmt: skip
        raise TypeError(f"concentration_step: {name} must be a contiguous float64 array of "
                        f"shape ({n},), updated in place")  # fmt: skip
    return a


def concentration_step(px, py, vol0, phi, s_int, gdot_int, t_int, cg: ConcGrid, prm,
                       work: np.ndarray | None = None) -> int:  # fmt: skip
    """Advance φ^s_p over a subcycle of length t_int (s); return the number of FV substeps taken.

    The engine's compiled 2-D step (``kernels_d2.concentration_step``) on points at (px, py) with
    reference volumes vol0 and the closure parameters ``prm`` (closures.pack_params or
    make_params). s_int[p], gdot_int[p] are the time integrals over the subcycle of the driving
    stress S (Pa·s) and of the shear rate γ̇ (dimensionless); they are zeroed on return. phi is
    updated in place (phi, s_int, gdot_int: contiguous float64). ``work``: the scratch of
    :func:`allocate_work` (allocated here if None). See the module docstring for steps (i)–(k).
    """
    from ..engine.codegen import kernels
    from ..engine.records import CONC, Points, Segregation

    k = kernels(2)
    n = len(px)
    phi = _f64("phi", phi, n)
    s_int = _f64("s_int", s_int, n)
    gdot_int = _f64("gdot_int", gdot_int, n)
    if work is None:
        work = allocate_work(cg)
    grid = np.zeros(1, dtype=CONC)
    grid["hc"] = cg.hc
    grid["origin"][0] = (cg.x0, cg.y0, 0.0)
    grid["cells"][0] = (cg.ncx, cg.ncy, 1)
    grid["periodic_x"] = cg.periodic_x
    prm = np.ascontiguousarray(prm, dtype=np.float64)
    seg = Segregation(grid=grid, prm=prm, prm_z=prm, work=work,
                      corner_cells=np.zeros((8, 3), dtype=np.int64), corner_weights=np.zeros(8))  # fmt: skip
    x = np.ascontiguousarray(np.stack([np.asarray(px, dtype=np.float64),
                                       np.asarray(py, dtype=np.float64)]))  # fmt: skip
    e1 = np.zeros(n)
    P = Points(x=x, v=np.zeros((2, n)), C=np.zeros((4, n)), mass=e1, vol0=np.ascontiguousarray(
        vol0, dtype=np.float64), J=e1, eps=np.zeros((4, n)), sig=np.zeros((4, n)), phi=phi,
        gf=e1, diag=np.zeros((6, n)), s_int=s_int, g_int=gdot_int, lg=np.zeros((4, n)),
        flags=np.zeros(n, dtype=np.int8), cursor=np.zeros(n, dtype=np.int32),
        x_old=np.zeros((2, 0)))  # fmt: skip
    return int(k.concentration_step(P, seg, float(t_int)))
