"""Compiled helpers the generated kernels (engine/kernels.py) import unchanged in 2-D and 3-D:
they do not depend on the dimension, so they are written once here, not in the template.

* ``_reduce_block`` and the rows ``B_*``: the scalar reduction after a block of the material pass;
* ``counting_sort`` and ``_balance``: the stable, parallel sort of the points into strips of cell
  rows and the split of one colour's strips into runs of equal work (P2G, docs/model.md §2);
* ``sidewall_drag``: the Coulomb body force of the 2-D sidewalls (Jop, Forterre & Pouliquen
  2005), shared by the MPM grid update and the column model;
* ``node_velocity``: the column model's node update;
* the constants of the fluidity step's cut-cell free surface and G2P (docs/model.md,
  "Nonlocal rheology").
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .records import COL_M, COL_U, COL_V

#: rows of a block's buffer in the material pass: shear rate, I, S, c + |v|, ν, failed (1.0)
B_GDOT, B_I, B_S, B_SPEED, B_NU, B_BAD, B_ROWS = range(7)

#: the free surface on the grid: a node's P2G mass fraction θ = m/(ρ h²) (B-spline weighted)
#: maps to the filled fraction of its control volume c = clamp(1.5 θ − 0.25, 0, 1) (exact for a
#: flat surface at the node, half a cell above and half a cell below it); nodes with c > 0 hold
#: fluidity, and c is their capacity in the finite-volume diffusion (a cut cell), so that the
#: zero-flux surface sits where the material ends, continuously in its position
FILL_SLOPE, FILL_OFFSET = 1.5, 0.25
#: floor on the capacity in the explicit update (a nearly empty surface node would otherwise set
#: a vanishing stable step)
CAPACITY_MIN = 0.25

#: fraction of the explicit diffusion limit h²/(4 D_max) used per sub-step
SAFETY = 0.9

#: floor of a point's g after the diffusion increment (see ``fluidity_step``)
TINY = 1e-300

#: PIC share of the G2P of g: g_p ← (1 − PIC)(g_p + Σ w Δg_i) + PIC Σ w g_i / Σ w. The increment
#: alone (FLIP) leaves the point-scale modes of g, which the grid cannot see, undamped, and a
#: point driven to g = 0 by a negative increment then stays there (the local growth from the seed
#: is slower than the increments); 5 % damps those modes within twenty updates and adds a
#: numerical diffusion of order PIC h²/Δt_g (≈ 1 % of A² d̄²/t₀ at the defaults)
PIC = 0.05


@njit(cache=True, error_model="numpy", inline="always")
def _reduce_block(lo, m, n, buf, diag, full):
    """Max c + |v|, max ν and the first failing point (n: none) of a block from its buffer; the
    diagnostics (``diag`` rows 1–5) of every point if ``full``, else of the failing ones."""
    smax = 0.0
    numax = 0.0
    bad = n
    for q in range(m):
        smax = max(smax, buf[B_SPEED, q])
        numax = max(numax, buf[B_NU, q])
        failed = buf[B_BAD, q] != 0.0
        if failed:
            bad = min(bad, lo + q)
        if full or failed:
            p = lo + q
            diag[1, p] = buf[B_GDOT, q]
            diag[2, p] = buf[B_I, q]
            diag[3, p] = buf[B_S, q]
            diag[4, p] = buf[B_SPEED, q]
            diag[5, p] = buf[B_NU, q]
    return smax, numax, bad


@njit(cache=True, error_model="numpy", inline="always")
def _count_chunk(c, nc, cursor, counts):
    """Histogram by strip of the points of chunk c of nc (row c of ``counts``)."""
    n = cursor.shape[0]
    for p in range(c * n // nc, (c + 1) * n // nc):
        counts[c, cursor[p]] += 1


@njit(cache=True, error_model="numpy", inline="always")
def _place_chunk(c, nc, cursor, counts, order):
    """Place the points of chunk c at their offsets (row c of ``counts``), in index order."""
    n = cursor.shape[0]
    for p in range(c * n // nc, (c + 1) * n // nc):
        s = cursor[p]
        order[counts[c, s]] = p
        counts[c, s] += 1


@njit(cache=True, error_model="numpy", parallel=True)
def counting_sort(cursor, strip_start, order, nchunks):
    """Stable counting sort of the points by strip ``cursor``: ``order`` lists them strip by strip
    and ``strip_start`` holds the strips' offsets.

    Parallel over contiguous chunks of the points (a histogram per chunk, one prefix sum over
    strip-major, chunk-minor counts, a placement per chunk): a stable sort has one result, so it
    does not depend on the number of chunks or threads. ``nchunks``: at most this many chunks
    (the time loop uses one per thread), of at least 4096 points; with one chunk no parallel
    region is launched (small N). Integer work only."""
    ns = strip_start.shape[0] - 1
    nc = max(1, min(nchunks, cursor.shape[0] // 4096))
    counts = np.zeros((nc, ns), dtype=np.int64)
    if nc == 1:
        _count_chunk(0, 1, cursor, counts)
    else:
        for c in prange(nc):
            _count_chunk(c, nc, cursor, counts)
    acc = 0
    for s in range(ns):
        strip_start[s] = acc
        for c in range(nc):
            k = counts[c, s]
            counts[c, s] = acc
            acc += k
    strip_start[ns] = acc
    if nc == 1:
        _place_chunk(0, 1, cursor, counts, order)
    else:
        for c in prange(nc):
            _place_chunk(c, nc, cursor, counts, order)


@njit(cache=True, error_model="numpy")
def _balance(strip_start, colour, nc, bounds):
    """Split the strips ``colour + 2k`` (k < nc) into len(bounds) − 1 runs of consecutive strips
    holding about equal numbers of points (one run per thread; empty strips above the free
    surface would otherwise leave a thread idle). Which thread scatters a strip does not change
    the result: strips of one colour share no node."""
    nt = bounds.shape[0] - 1
    total = 0
    for k in range(nc):
        s = colour + 2 * k
        total += strip_start[s + 1] - strip_start[s]
    bounds[0] = 0
    j = 1
    acc = 0
    for k in range(nc):
        while j < nt and acc * nt >= j * total:
            bounds[j] = k
            j += 1
        s = colour + 2 * k
        acc += strip_start[s + 1] - strip_start[s]
    while j <= nt:
        bounds[j] = nc
        j += 1


@njit(cache=True, error_model="numpy", inline="always")
def sidewall_friction(vx, vy, dvmax):
    """Coulomb update v ← v − min(|v|, Δv_max) v/|v| (docs/model.md §2): never reverses v."""
    speed = math.sqrt(vx * vx + vy * vy)
    if speed <= dvmax:
        return 0.0, 0.0
    s = 1.0 - dvmax / speed
    return vx * s, vy * s


@njit(cache=True, error_model="numpy", inline="always")
def sidewall_drag(vx, vy, sw, sw0, uw, dt, vp, im):
    """The sidewall Coulomb body force over one step (docs/model.md §2), shared by the MPM grid
    update and the column model: Δv_max = Δt (2 K_w μ_w(u)/W) (Σ V p)/m with
    μ_w(u) = μ_w0 + (μ_w∞ − μ_w0) u/(u + u_w) (``sw``, ``sw0`` = 2 K_w μ/W; u_w > 0), or the
    constant μ_w (u_w = 0); ``vp`` = Σ V p of the node, ``im`` = 1/m. Never reverses v."""
    f = sw
    if uw > 0.0:
        s = math.sqrt(vx * vx + vy * vy)
        f = sw0 + (sw - sw0) * s / (s + uw)
    return sidewall_friction(vx, vy, dt * f * vp * im)


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
