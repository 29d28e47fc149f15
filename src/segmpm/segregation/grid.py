"""The extra Eulerian concentration grid and the compiled species-transport step (seed Fig. 1 i–k).

``concentration_step`` advances the small-grain concentration φ^s_p of the material points over one
subcycle of length t_int (docs/segregation.md §2):

(i)   MP → grid with tent (bilinear) weights w_cp to the cell centres (Σ_c w_cp = 1), restricted
      to the active cells (raw fill θ_c ≥ θ_min) and renormalised (``mp_weights``):
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
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from segmpm.segregation.closures import (
    M_NONE,
    P_D_LARGE,
    P_D_SMALL,
    P_FILL_MIN,
    P_FLUX,
    P_MODEL,
    P_SAFETY,
    face_rates,
    face_velocity_diffusivity,
)


class ConcGrid(NamedTuple):
    """Geometry of the concentration grid (square cells h_c × h_c, centres at x0 + (i + ½) h_c)."""

    x0: float  #: x of the lower-left corner of cell (0, 0), m
    y0: float  #: y of the lower-left corner of cell (0, 0), m
    hc: float  #: cell size h_c, m
    ncx: int  #: cells in x
    ncy: int  #: cells in y
    periodic_x: int  #: 1: periodic in x with period ncx·h_c; 0: closed (zero flux) in x


# indices of the scratch arrays returned by allocate_work (all float64, shape (ncx, ncy))
W_VOL = 0  #: V_c = Σ w V⁰
W_SUM_S = 1  #: Σ w V⁰ φ (small-grain volume in the cell)
W_SUM_L = 2  #: Σ w V⁰ (1 − φ) (large-grain volume in the cell)
W_PHI = 3  #: φ_c, evolving over the substeps
W_PHI0 = 4  #: φ_c at the start of the call
W_S = 5  #: S_c, time-averaged driving stress, Pa
W_GDOT = 6  #: γ̇_c, time-averaged shear rate, 1/s
W_AX = 7  #: rate a of the x-face between (i, j) and (i+1, j)
W_BX = 8  #: rate b of that x-face
W_AY = 9  #: rate a of the y-face between (i, j) and (i, j+1)
W_BY = 10  #: rate b of that y-face
W_THETA = 11  #: fill fraction θ_c
W_DIV = 12  #: net outflow Σ_faces F of a substep
W_ACT = 13  #: 1.0 where the cell is active (raw fill θ ≥ θ_min), else 0.0
N_WORK = 14


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


def allocate_work(cg: ConcGrid) -> tuple[np.ndarray, ...]:
    """Every scratch array of ``concentration_step`` (indices ``W_*``), allocated once."""
    return tuple(np.zeros((cg.ncx, cg.ncy), dtype=np.float64) for _ in range(N_WORK))


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


@njit(cache=True, error_model="numpy")
def mp_weights(x: float, y: float, cg: ConcGrid, act: np.ndarray):
    """Cells (i0, i1, j0, j1) and weights (w00, w01, w10, w11) of a material point.

    Bilinear tent weights, restricted to the active cells and renormalised to sum to one, so that a
    point next to an inactive (empty, ghost or partly filled) cell follows its active neighbours
    fully instead of being damped by a cell whose φ_c never changes. A point with no active cell
    keeps its raw weights (it exchanges nothing). The same weights serve steps (i) and (k), which
    is what makes the mapping conservative.
    """
    i0, i1, wx0, wx1 = tent_weights(x, cg.x0, cg.hc, cg.ncx, cg.periodic_x)
    j0, j1, wy0, wy1 = tent_weights(y, cg.y0, cg.hc, cg.ncy, 0)
    w00 = wx0 * wy0
    w01 = wx0 * wy1
    w10 = wx1 * wy0
    w11 = wx1 * wy1
    a00 = w00 * act[i0, j0]
    a01 = w01 * act[i0, j1]
    a10 = w10 * act[i1, j0]
    a11 = w11 * act[i1, j1]
    tot = a00 + a01 + a10 + a11
    if tot > 0.0:
        return i0, i1, j0, j1, a00 / tot, a01 / tot, a10 / tot, a11 / tot
    return i0, i1, j0, j1, w00, w01, w10, w11


@njit(cache=True, error_model="numpy")
def concentration_step(px, py, vol0, phi, s_int, gdot_int, t_int, cg, prm, work) -> int:
    """Advance φ^s_p over a subcycle of length t_int (s); return the number of FV substeps taken.

    s_int[p], gdot_int[p] are the time integrals over the subcycle of the driving stress S (Pa·s)
    and of the shear rate γ̇ (dimensionless); they are zeroed on return. phi is updated in place.
    See the module docstring for steps (i)–(k).
    """
    npart = px.shape[0]
    model = int(prm[P_MODEL])
    if model == M_NONE or not (t_int > 0.0):
        for p in range(npart):
            s_int[p] = 0.0
            gdot_int[p] = 0.0
        return 0

    hc = cg.hc
    ncx = cg.ncx
    ncy = cg.ncy
    per = cg.periodic_x
    vol = work[W_VOL]
    sum_s = work[W_SUM_S]
    sum_l = work[W_SUM_L]
    phic = work[W_PHI]
    phi0 = work[W_PHI0]
    sc = work[W_S]
    gc = work[W_GDOT]
    ax = work[W_AX]
    bx = work[W_BX]
    ay = work[W_AY]
    by = work[W_BY]
    theta = work[W_THETA]
    div = work[W_DIV]

    # ---- (i) MP → grid ----------------------------------------------------------------------
    area = hc * hc
    fill_min = prm[P_FILL_MIN]
    act = work[W_ACT]
    # pass 1: raw tent-weight fill θ_c decides which cells are active
    for i in range(ncx):
        for j in range(ncy):
            vol[i, j] = 0.0
            act[i, j] = 1.0
    for p in range(npart):
        i0, i1, j0, j1, w00, w01, w10, w11 = mp_weights(px[p], py[p], cg, act)
        v = vol0[p]
        vol[i0, j0] += w00 * v
        vol[i0, j1] += w01 * v
        vol[i1, j0] += w10 * v
        vol[i1, j1] += w11 * v
    for i in range(ncx):
        for j in range(ncy):
            act[i, j] = 1.0 if vol[i, j] >= fill_min * area else 0.0
            vol[i, j] = 0.0
            sum_s[i, j] = 0.0
            sum_l[i, j] = 0.0
            sc[i, j] = 0.0
            gc[i, j] = 0.0
    # pass 2: weights restricted to the active cells (mp_weights), the ones step (k) uses
    for p in range(npart):
        i0, i1, j0, j1, w00, w01, w10, w11 = mp_weights(px[p], py[p], cg, act)
        v = vol0[p]
        f = phi[p]
        sp = s_int[p]
        gp = gdot_int[p]
        for c in range(4):
            if c == 0:
                ii, jj, wv = i0, j0, w00 * v
            elif c == 1:
                ii, jj, wv = i0, j1, w01 * v
            elif c == 2:
                ii, jj, wv = i1, j0, w10 * v
            else:
                ii, jj, wv = i1, j1, w11 * v
            vol[ii, jj] += wv
            sum_s[ii, jj] += wv * f
            sum_l[ii, jj] += wv * (1.0 - f)
            sc[ii, jj] += wv * sp
            gc[ii, jj] += wv * gp
    for i in range(ncx):
        for j in range(ncy):
            vc = vol[i, j]
            if vc > 0.0:
                f = sum_s[i, j] / vc
                phic[i, j] = min(1.0, max(0.0, f))
                sc[i, j] /= vc * t_int
                gc[i, j] /= vc * t_int
            else:
                phic[i, j] = 0.0
            phi0[i, j] = phic[i, j]
            theta[i, j] = vc / area

    # ---- (j) face coefficients, frozen over the subcycle ------------------------------------
    flux_kind = int(prm[P_FLUX])
    d_s = prm[P_D_SMALL]
    d_l = prm[P_D_LARGE]
    for i in range(ncx):
        ib = i + 1
        if ib == ncx:
            ib = 0 if per == 1 else -1
        for j in range(ncy):
            active = act[i, j] > 0.0
            # x-face (i, j) | (ib, j)
            ax[i, j] = 0.0
            bx[i, j] = 0.0
            if active and ib >= 0 and ib != i and act[ib, j] > 0.0:
                da = d_s * phic[i, j] + d_l * (1.0 - phic[i, j])
                db = d_s * phic[ib, j] + d_l * (1.0 - phic[ib, j])
                w, d = face_velocity_diffusivity(
                    prm, sc[i, j], sc[ib, j], gc[i, j], gc[ib, j], da, db, hc, 0
                )
                ax[i, j], bx[i, j] = face_rates(w, d, hc, flux_kind)
            # y-face (i, j) | (i, j+1)
            ay[i, j] = 0.0
            by[i, j] = 0.0
            if active and j + 1 < ncy and act[i, j + 1] > 0.0:
                da = d_s * phic[i, j] + d_l * (1.0 - phic[i, j])
                db = d_s * phic[i, j + 1] + d_l * (1.0 - phic[i, j + 1])
                w, d = face_velocity_diffusivity(
                    prm, sc[i, j], sc[i, j + 1], gc[i, j], gc[i, j + 1], da, db, hc, 1
                )
                ay[i, j], by[i, j] = face_rates(w, d, hc, flux_kind)

    # stable step: Σ_faces ∂(outflow)/∂φ_c ≤ Σ_faces max(a, b) must not exceed θ_c h_c / Δt_c
    rate_max = 0.0
    bad = False
    for i in range(ncx):
        im = i - 1
        if im < 0:
            im = ncx - 1 if per == 1 else -1
        for j in range(ncy):
            if act[i, j] == 0.0:
                continue
            r = max(ax[i, j], bx[i, j]) + max(ay[i, j], by[i, j])
            if im >= 0:
                r += max(ax[im, j], bx[im, j])
            if j > 0:
                r += max(ay[i, j - 1], by[i, j - 1])
            r /= theta[i, j] * hc
            if r != r:
                bad = True
            elif r > rate_max:
                rate_max = r
    nsub = 0
    if bad or not math.isfinite(rate_max):
        nsub = 1  # NaN/inf coefficients: one step, so the NaN reaches φ and the engine's check
    elif rate_max > 0.0:
        nsub = max(1, int(math.ceil(t_int * rate_max / prm[P_SAFETY])))
    dt = t_int / nsub if nsub > 0 else 0.0

    for _ in range(nsub):
        for i in range(ncx):
            for j in range(ncy):
                div[i, j] = 0.0
        for i in range(ncx):
            ib = i + 1
            if ib == ncx:
                ib = 0 if per == 1 else -1
            for j in range(ncy):
                fa = phic[i, j]
                a = ax[i, j]
                b = bx[i, j]
                if ib >= 0 and (a != 0.0 or b != 0.0):
                    fb = phic[ib, j]
                    flux = a * fa * (1.0 - fb) - b * fb * (1.0 - fa)
                    div[i, j] += flux
                    div[ib, j] -= flux
                a = ay[i, j]
                b = by[i, j]
                if a != 0.0 or b != 0.0:
                    fb = phic[i, j + 1]
                    flux = a * fa * (1.0 - fb) - b * fb * (1.0 - fa)
                    div[i, j] += flux
                    div[i, j + 1] -= flux
        for i in range(ncx):
            for j in range(ncy):
                if div[i, j] != 0.0:
                    phic[i, j] -= dt * div[i, j] / (theta[i, j] * hc)

    # ---- (k) grid → MP, incremental and bound-preserving ------------------------------------
    if nsub > 0:
        for i in range(ncx):
            for j in range(ncy):
                # Δφ_c, reusing the divergence array
                div[i, j] = phic[i, j] - phi0[i, j]
        for p in range(npart):
            i0, i1, j0, j1, w00, w01, w10, w11 = mp_weights(px[p], py[p], cg, act)
            f = phi[p]
            dphi = 0.0
            for c in range(4):
                if c == 0:
                    ii, jj, wt = i0, j0, w00
                elif c == 1:
                    ii, jj, wt = i0, j1, w01
                elif c == 2:
                    ii, jj, wt = i1, j0, w10
                else:
                    ii, jj, wt = i1, j1, w11
                dc = div[ii, jj]
                # ω = (1 − φ_p)/(1 − φ_c) with 1 − φ_c = Σ w V⁰ (1 − φ)/V_c, or φ_p/φ_c
                if dc > 0.0:
                    if sum_l[ii, jj] > 0.0:
                        dphi += wt * dc * (1.0 - f) * vol[ii, jj] / sum_l[ii, jj]
                elif dc < 0.0:
                    if sum_s[ii, jj] > 0.0:
                        dphi += wt * dc * f * vol[ii, jj] / sum_s[ii, jj]
            f += dphi
            # exact arithmetic keeps f in [0, 1]; the clamp only removes round-off
            phi[p] = min(1.0, max(0.0, f))

    for p in range(npart):
        s_int[p] = 0.0
        gdot_int[p] = 0.0
    return nsub
