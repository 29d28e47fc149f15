"""Particle ↔ grid transfers: P2G, grid momentum update, G2P (docs/model.md §2).

Points are struct-of-arrays: ``x`` (2, N), ``v`` (2, N), ``C`` (4, N) the APIC affine matrix
(C00, C01, C10, C11), ``sig`` (4, N) Cauchy stress (xx, yy, xy, zz). Grid arrays are
(N_x, N_y[, k]).

P2G is parallel and deterministic whatever the thread count: points are sorted into horizontal
strips ``STRIP`` = 3 cells high. A point in cell row r touches node rows r − 1 … r + 2, so a strip
touches its own rows and one below and two above; strips two apart never share a node. Strips of
one colour (even, then odd) scatter concurrently, each its points in index order without atomics,
and every node receives its contributions in the same order on any number of threads.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .boundary import apply_bc, sidewall_drag
from .params import (
    BC_NOSLIP,
    G_BASE_KIND,
    G_BASE_Y,
    G_GX,
    G_GY,
    G_H,
    G_IMAGES,
    G_PERIODIC,
    G_SIDEWALL,
    G_SW_SLOW,
    G_SW_SPEED,
    G_X0,
    G_XHI,
    G_XHI_KIND,
    G_XLO,
    G_XLO_KIND,
    G_Y0,
)
from .shape import bspline2_frac


@njit(cache=True, error_model="numpy", inline="always")
def _wrap(i, n):
    """Periodic node index for i in [−n, 2n) without an integer division."""
    if i < 0:
        return i + n
    if i >= n:
        return i - n
    return i


#: cell rows per P2G strip (must be ≥ 3 for strips of one colour to share no node)
STRIP = 3

#: nodal accumulator fields of P2G: mass, momentum, internal force, and Σ w V p (the pressure
#: integral of the sidewall friction force)
N_MASS, N_MX, N_MY, N_FX, N_FY, N_VP, N_FIELDS = range(7)

#: lanes of the nodal velocity array ``gv`` (N_x, N_y, 4): the updated velocity v* and the old
#: velocity m v / m of the FLIP increment, each with the boundary conditions applied
V_X, V_Y, V_OX, V_OY, V_LANES = range(5)


@njit(cache=True, error_model="numpy", inline="always")
def strip_of(y, y0, ih, nstrips):
    """P2G strip (``STRIP`` cell rows) of a point at height y, clamped to [0, nstrips).

    ``ih`` = 1/h: the grid coordinate (y − y0) ih is computed exactly as in the P2G stencil, so
    that a point's strip and the node rows it scatters to always agree."""
    s = int(math.floor((y - y0) * ih)) // STRIP
    return min(max(s, 0), nstrips - 1)


@njit(cache=True, error_model="numpy", parallel=True)
def strip_index(py, gp, cursor, nstrips):
    """``cursor[p]``: the strip of every point (the time loop gets it from G2P afterwards)."""
    ih = 1.0 / gp[G_H]
    y0 = gp[G_Y0]
    for p in prange(py.shape[0]):
        cursor[p] = strip_of(py[p], y0, ih, nstrips)


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
def sort_into_strips(py, gp, strip_start, cursor, order):
    """Strip of every point and the stable counting sort (``strip_index`` + ``counting_sort``)."""
    strip_index(py, gp, cursor, strip_start.shape[0] - 1)
    counting_sort(cursor, strip_start, order, 1)


@njit(cache=True, error_model="numpy", inline="always")
def _scatter_node(g, k, w, gx, gy, m, mvx, mvy, sxx, sxy, syy, vp, force):
    """Add one point's share to the node whose fields start at ``g[k]`` (flat grid)."""
    mw = m * w
    g[k + N_MASS] += mw
    g[k + N_MX] += mw * mvx
    g[k + N_MY] += mw * mvy
    if force:
        g[k + N_FX] += sxx * gx + sxy * gy
        g[k + N_FY] += sxy * gx + syy * gy
    g[k + N_VP] += w * vp


@njit(cache=True, error_model="numpy", inline="always")
def _scatter_column(g, k, wa, da, ddx, wy0, wy1, wy2, dy0, dy1, dy2, ey0, ey1, ey2, m, vx, vy,
                    c00, c01, c10, c11, sxx, sxy, syy, vp, force):  # fmt: skip
    """P2G onto the three nodes of one grid column (``k``: flat offset of its lowest node;
    ``ey_b`` = y_b − y_p)."""
    mvx = vx + c00 * ddx
    mvy = vy + c10 * ddx
    _scatter_node(g, k, wa * wy0, da * wy0, wa * dy0, m, mvx + c01 * ey0, mvy + c11 * ey0,
                  sxx, sxy, syy, vp, force)  # fmt: skip
    _scatter_node(g, k + N_FIELDS, wa * wy1, da * wy1, wa * dy1, m, mvx + c01 * ey1,
                  mvy + c11 * ey1, sxx, sxy, syy, vp, force)  # fmt: skip
    _scatter_node(g, k + 2 * N_FIELDS, wa * wy2, da * wy2, wa * dy2, m, mvx + c01 * ey2,
                  mvy + c11 * ey2, sxx, sxy, syy, vp, force)  # fmt: skip


@njit(cache=True, error_model="numpy", inline="always")
def _columns(bx, nx, periodic):
    """The three node columns of a stencil with base column ``bx`` (periodic: wrapped)."""
    if not periodic:
        return bx, bx + 1, bx + 2
    return _wrap(bx, nx), _wrap(bx + 1, nx), _wrap(bx + 2, nx)


@njit(cache=True, error_model="numpy", inline="always")
def _scatter_point(p, x, v, C, mass, vol0, J, sig, pres, g, ih, h, x0, y0, nx, ny, periodic,
                   force):  # fmt: skip
    """P2G of one point onto its 3 × 3 nodes: mass, APIC momentum, internal force −V σ·∇w and
    the sidewall pressure integral w V p (``g``: the flat grid, N_FIELDS per node)."""
    xp = x[0, p]
    yp = x[1, p]
    bx, wx0, wx1, wx2, dx0, dx1, dx2, fx = bspline2_frac((xp - x0) * ih)
    by, wy0, wy1, wy2, dy0, dy1, dy2, fy = bspline2_frac((yp - y0) * ih)
    # node offsets y_b − y_p in metres
    ey0 = -fy * h
    ey1 = (1.0 - fy) * h
    ey2 = (2.0 - fy) * h
    m = mass[p]
    vol = vol0[p] * J[p]
    # −V σ·∇w with ∇w per grid unit: the 1/h is folded into the stress
    fv = -vol * ih
    sxx = fv * sig[0, p]
    syy = fv * sig[1, p]
    sxy = fv * sig[2, p]
    vp = vol * pres[p]
    vx = v[0, p]
    vy = v[1, p]
    c00 = C[0, p]
    c01 = C[1, p]
    c10 = C[2, p]
    c11 = C[3, p]
    i0, i1, i2 = _columns(bx, nx, periodic)
    _scatter_column(g, (i0 * ny + by) * N_FIELDS, wx0, dx0, -fx * h, wy0, wy1, wy2, dy0, dy1,
                    dy2, ey0, ey1, ey2, m, vx, vy, c00, c01, c10, c11, sxx, sxy, syy, vp,
                    force)  # fmt: skip
    _scatter_column(g, (i1 * ny + by) * N_FIELDS, wx1, dx1, (1.0 - fx) * h, wy0, wy1, wy2, dy0,
                    dy1, dy2, ey0, ey1, ey2, m, vx, vy, c00, c01, c10, c11, sxx, sxy, syy, vp,
                    force)  # fmt: skip
    _scatter_column(g, (i2 * ny + by) * N_FIELDS, wx2, dx2, (2.0 - fx) * h, wy0, wy1, wy2, dy0,
                    dy1, dy2, ey0, ey1, ey2, m, vx, vy, c00, c01, c10, c11, sxx, sxy, syy, vp,
                    force)  # fmt: skip


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


@njit(cache=True, error_model="numpy", parallel=True, fastmath={"contract"})
def p2g(x, v, C, mass, vol0, J, sig, pres, gp, grid, strip_start, order, bounds, with_force):
    """Scatter mass, APIC momentum, internal force −Σ V σ·∇w, and Σ w V p (sidewall friction).

    ``grid`` (N_x, N_y, N_FIELDS); ``pres`` the pressure p of each point; ``bounds``
    (threads + 1): work array; its length sets the number of balanced strip runs."""
    g = grid.reshape(grid.size)
    g[:] = 0.0
    ns = strip_start.shape[0] - 1
    h = gp[G_H]
    ih = 1.0 / h
    x0 = gp[G_X0]
    y0 = gp[G_Y0]
    nx = grid.shape[0]
    ny = grid.shape[1]
    periodic = gp[G_PERIODIC] != 0.0
    nt = bounds.shape[0] - 1
    for colour in range(2):
        nc = (ns - colour + 1) // 2
        _balance(strip_start, colour, nc, bounds)
        for t in prange(nt):
            for k in range(bounds[t], bounds[t + 1]):
                s = colour + 2 * k
                for i in range(strip_start[s], strip_start[s + 1]):
                    _scatter_point(order[i], x, v, C, mass, vol0, J, sig, pres, g, ih, h,
                                   x0, y0, nx, ny, periodic, with_force)  # fmt: skip


@njit(cache=True, error_model="numpy")
def _node_plane(coord, origin, h, n):
    """Index of the node plane at ``coord`` if it is one (and not the first or last), else −1."""
    r = (coord - origin) / h
    k = int(math.floor(r + 0.5))
    if abs(r - k) > 1e-6 or k < 1 or k > n - 2:
        return -1
    return k


@njit(cache=True, error_model="numpy")
def image_planes(gp, nx, ny):
    """Node indices (j_base, i_lo, i_hi) of the no-slip walls that get image nodes, −1 if none.

    Images apply to no-slip walls that lie on a node plane, when ``G_IMAGES`` is set.
    """
    jb = -1
    il = -1
    ih = -1
    if gp[G_IMAGES] == 0.0:
        return jb, il, ih
    h = gp[G_H]
    if int(gp[G_BASE_KIND]) == BC_NOSLIP:
        jb = _node_plane(gp[G_BASE_Y], gp[G_Y0], h, ny)
    if gp[G_PERIODIC] == 0.0:
        if int(gp[G_XLO_KIND]) == BC_NOSLIP:
            il = _node_plane(gp[G_XLO], gp[G_X0], h, nx)
        if int(gp[G_XHI_KIND]) == BC_NOSLIP:
            ih = _node_plane(gp[G_XHI], gp[G_X0], h, nx)
    return jb, il, ih


@njit(cache=True, error_model="numpy", inline="always")
def _fold(grid, ig, jg, im, jm, gx, gy):
    m = grid[ig, jg, N_MASS]
    grid[im, jm, N_MASS] += m
    grid[im, jm, N_MX] -= grid[ig, jg, N_MX]
    grid[im, jm, N_MY] -= grid[ig, jg, N_MY]
    # the weight on the image node is odd too: (m − m_g) g in all, with m g added later
    grid[im, jm, N_FX] -= grid[ig, jg, N_FX] + 2.0 * m * gx
    grid[im, jm, N_FY] -= grid[ig, jg, N_FY] + 2.0 * m * gy
    grid[im, jm, N_VP] += grid[ig, jg, N_VP]
    for f in range(N_FIELDS):
        grid[ig, jg, f] = 0.0


@njit(cache=True, error_model="numpy")
def image_pairs(gp, nx, ny):
    """The image nodes of the no-slip walls, in the order they are folded: rows
    (i, j) of a node behind a wall, (i_m, j_m) of its mirror node, and 1 if the mirror lies in the
    grid (else the wall node stands in as mirror for the velocity and nothing is folded).
    The base comes first, then the walls x = x_lo and x = x_hi, so a corner node behind two walls
    is reflected twice. Computed once per call of the time loop."""
    jb, il, ih = image_planes(gp, nx, ny)
    count = 0
    if jb > 0:
        count += nx * jb
    if il > 0:
        count += ny * il
    if ih > 0:
        count += ny * (nx - 1 - ih)
    pairs = np.empty((count, 5), dtype=np.int64)
    r = 0
    if jb > 0:
        for i in range(nx):
            for k in range(1, jb + 1):
                inside = jb + k < ny
                pairs[r] = (i, jb - k, i, jb + k if inside else jb, 1 if inside else 0)
                r += 1
    if il > 0:
        for j in range(ny):
            for k in range(1, il + 1):
                inside = il + k < nx
                pairs[r] = (il - k, j, il + k if inside else il, j, 1 if inside else 0)
                r += 1
    if ih > 0:
        for j in range(ny):
            for k in range(1, nx - ih):
                inside = ih - k >= 0
                pairs[r] = (ih + k, j, ih - k if inside else ih, j, 1 if inside else 0)
                r += 1
    return pairs


@njit(cache=True, error_model="numpy")
def fold_images(grid, pairs, gx, gy):
    """Image nodes of no-slip walls (docs/model.md, "No-slip walls"): the P2G sums of a node
    behind the wall fold onto its mirror node, with the velocity of the node behind the wall
    slaved to minus that of its mirror (``mirror_images``), i.e. the Galerkin system on the odd
    extension of the velocity across the wall: mass +, momentum −, force − (gravity included).
    Without it the B-spline basis is one-sided at the wall and the wall kinematics are first
    order in h. ``pairs`` from ``image_pairs``; ``gx, gy``: the gravity applied to the nodes
    afterwards, per unit mass."""
    for r in range(pairs.shape[0]):
        if pairs[r, 4] != 0:
            _fold(grid, pairs[r, 0], pairs[r, 1], pairs[r, 2], pairs[r, 3], gx, gy)


@njit(cache=True, error_model="numpy")
def mirror_images(gv, pairs):
    """Nodal velocities (every lane of ``gv``) behind no-slip walls: minus those of their mirror
    nodes (``fold_images``)."""
    for r in range(pairs.shape[0]):
        ig, jg, im, jm = pairs[r, 0], pairs[r, 1], pairs[r, 2], pairs[r, 3]
        for lane in range(gv.shape[2]):
            gv[ig, jg, lane] = -gv[im, jm, lane]


@njit(cache=True, error_model="numpy", parallel=True)
def grid_update(gp, grid, gv, dt, ramp, sidewall_on):
    """Nodal velocities: v* = (m v + Δt (f + m g))/m, sidewall friction, then boundaries.

    ``ramp`` ∈ [0, 1] scales the tangential gravity and the sidewall force (start-up ramp).
    ``gv`` (N_x, N_y, 4) receives v* in lanes V_X, V_Y and the old velocity m v / m, with the
    same boundary conditions (FLIP), in lanes V_OX, V_OY.
    """
    nx = grid.shape[0]
    ny = grid.shape[1]
    h = gp[G_H]
    x0 = gp[G_X0]
    y0 = gp[G_Y0]
    gx = gp[G_GX] * ramp
    gy = gp[G_GY]
    sw = gp[G_SIDEWALL] * ramp
    uw = gp[G_SW_SPEED]
    sw0 = gp[G_SW_SLOW] * ramp if uw > 0.0 else sw
    for i in prange(nx):
        xn = x0 + i * h
        for j in range(ny):
            m = grid[i, j, N_MASS]
            if m <= 0.0:
                for lane in range(V_LANES):
                    gv[i, j, lane] = 0.0
                continue
            im = 1.0 / m
            vox = grid[i, j, N_MX] * im
            voy = grid[i, j, N_MY] * im
            vx = vox + dt * (grid[i, j, N_FX] * im + gx)
            vy = voy + dt * (grid[i, j, N_FY] * im + gy)
            if sidewall_on and (sw > 0.0 or sw0 > 0.0):
                # Coulomb body force 2 μ_w K_w p / W per unit volume: its Galerkin integral
                # Σ w V p over the nodal mass is the pressure over density at the node
                vp = grid[i, j, N_VP]
                if vp > 0.0:
                    vx, vy = sidewall_drag(vx, vy, sw, sw0, uw, dt, vp, im)
            yn = y0 + j * h
            vx, vy = apply_bc(gp, xn, yn, vx, vy)
            # the boundary also constrains the old velocity, so that the FLIP increment on a
            # constrained node is only the physical change: otherwise zeroing a node's projected
            # velocity every step would act as a drag ∝ 1/Δt on the points near the wall
            vox, voy = apply_bc(gp, xn, yn, vox, voy)
            gv[i, j, V_X] = vx
            gv[i, j, V_Y] = vy
            gv[i, j, V_OX] = vox
            gv[i, j, V_OY] = voy


@njit(cache=True, error_model="numpy", parallel=True)
def momentum_to_velocity(gp, grid, gv):
    """MUSL remap: nodal velocity (lanes V_X, V_Y) from the re-scattered point momenta, with the
    boundaries."""
    nx = grid.shape[0]
    ny = grid.shape[1]
    h = gp[G_H]
    for i in prange(nx):
        for j in range(ny):
            m = grid[i, j, N_MASS]
            if m <= 0.0:
                gv[i, j, V_X] = 0.0
                gv[i, j, V_Y] = 0.0
                continue
            vx, vy = apply_bc(
                gp, gp[G_X0] + i * h, gp[G_Y0] + j * h, grid[i, j, N_MX] / m, grid[i, j, N_MY] / m
            )
            gv[i, j, V_X] = vx
            gv[i, j, V_Y] = vy


@njit(cache=True, error_model="numpy", inline="always")
def _gather_column(g, k, wy0, wy1, wy2, dy0, dy1, dy2, ey0, ey1, ey2):
    """Sums over the three nodes of one column (``k``: flat offset of the lowest node's lanes):
    Σ w_b u (4 lanes), Σ w_b' u and Σ e_b u with e_b = w_b (y_b − y_p)/h (velocity lanes)."""
    a0 = g[k]
    a1 = g[k + 1]
    a2 = g[k + 2]
    a3 = g[k + 3]
    b0 = g[k + 4]
    b1 = g[k + 5]
    b2 = g[k + 6]
    b3 = g[k + 7]
    c0 = g[k + 8]
    c1 = g[k + 9]
    c2 = g[k + 10]
    c3 = g[k + 11]
    return (
        wy0 * a0 + wy1 * b0 + wy2 * c0,
        wy0 * a1 + wy1 * b1 + wy2 * c1,
        wy0 * a2 + wy1 * b2 + wy2 * c2,
        wy0 * a3 + wy1 * b3 + wy2 * c3,
        dy0 * a0 + dy1 * b0 + dy2 * c0,
        dy0 * a1 + dy1 * b1 + dy2 * c1,
        ey0 * a0 + ey1 * b0 + ey2 * c0,
        ey0 * a1 + ey1 * b1 + ey2 * c1,
    )


@njit(cache=True, error_model="numpy", inline="always")
def gather(px, py, g, ih, x0, y0, nx, ny, periodic):
    """G2P at (px, py) from the flat nodal velocities ``g`` (lanes of ``gv``), separably: column
    sums first, then across the columns. Returns Σ w v_i; the APIC matrix
    C_p = (4/h²) Σ w v_i (x_i − x_p)ᵀ; L_p = Σ v_i ⊗ ∇w_i; Σ w v_i^old (the old velocity lanes,
    for the FLIP increment): (vx, vy, C00, C01, C10, C11, L00, L01, L10, L11, ox, oy)."""
    bx, wx0, wx1, wx2, dx0, dx1, dx2, fx = bspline2_frac((px - x0) * ih)
    by, wy0, wy1, wy2, dy0, dy1, dy2, fy = bspline2_frac((py - y0) * ih)
    # w_b (y_b − y_p) / h: node b lies at (b − f_y) h
    ey0 = -fy * wy0
    ey1 = (1.0 - fy) * wy1
    ey2 = (2.0 - fy) * wy2
    i0, i1, i2 = _columns(bx, nx, periodic)
    a0, a1, a2, a3, a4, a5, a6, a7 = _gather_column(
        g, (i0 * ny + by) * V_LANES, wy0, wy1, wy2, dy0, dy1, dy2, ey0, ey1, ey2
    )
    b0, b1, b2, b3, b4, b5, b6, b7 = _gather_column(
        g, (i1 * ny + by) * V_LANES, wy0, wy1, wy2, dy0, dy1, dy2, ey0, ey1, ey2
    )
    c0, c1, c2, c3, c4, c5, c6, c7 = _gather_column(
        g, (i2 * ny + by) * V_LANES, wy0, wy1, wy2, dy0, dy1, dy2, ey0, ey1, ey2
    )
    ex0 = -fx * wx0
    ex1 = (1.0 - fx) * wx1
    ex2 = (2.0 - fx) * wx2
    k = 4.0 * ih
    return (
        wx0 * a0 + wx1 * b0 + wx2 * c0,
        wx0 * a1 + wx1 * b1 + wx2 * c1,
        k * (ex0 * a0 + ex1 * b0 + ex2 * c0),
        k * (wx0 * a6 + wx1 * b6 + wx2 * c6),
        k * (ex0 * a1 + ex1 * b1 + ex2 * c1),
        k * (wx0 * a7 + wx1 * b7 + wx2 * c7),
        ih * (dx0 * a0 + dx1 * b0 + dx2 * c0),
        ih * (wx0 * a4 + wx1 * b4 + wx2 * c4),
        ih * (dx0 * a1 + dx1 * b1 + dx2 * c1),
        ih * (wx0 * a5 + wx1 * b5 + wx2 * c5),
        wx0 * a2 + wx1 * b2 + wx2 * c2,
        wx0 * a3 + wx1 * b3 + wx2 * c3,
    )
