"""Particle ↔ grid transfers: P2G, grid momentum update, G2P (physics.md §5.2).

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

from .boundary import apply_bc, sidewall_friction
from .params import (
    BC_NOSLIP,
    G_BASE_KIND,
    G_BASE_Y,
    G_GX,
    G_GY,
    G_H,
    G_IMAGES,
    G_NX,
    G_PERIODIC,
    G_SIDEWALL,
    G_X0,
    G_XHI,
    G_XHI_KIND,
    G_XLO,
    G_XLO_KIND,
    G_Y0,
)
from .shape import bspline2


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

#: nodal accumulator fields of P2G
N_MASS, N_MX, N_MY, N_FX, N_FY, N_MP, N_MRHO, N_FIELDS = range(8)


@njit(cache=True, error_model="numpy", inline="always")
def strip_of(y, y0, h, nstrips):
    """P2G strip (``STRIP`` cell rows) of a point at height y, clamped to [0, nstrips)."""
    s = int(math.floor((y - y0) / h)) // STRIP
    return min(max(s, 0), nstrips - 1)


@njit(cache=True, error_model="numpy", parallel=True)
def strip_index(py, gp, cursor, nstrips):
    """``cursor[p]``: the strip of every point (the time loop gets it from G2P afterwards)."""
    h = gp[G_H]
    y0 = gp[G_Y0]
    for p in prange(py.shape[0]):
        cursor[p] = strip_of(py[p], y0, h, nstrips)


@njit(cache=True, error_model="numpy")
def counting_sort(cursor, strip_start, order):
    """Stable counting sort of the points by strip ``cursor``: ``order`` lists them strip by strip
    and ``strip_start`` holds the strips' offsets (integer work only, so independent of the
    thread count)."""
    ns = strip_start.shape[0] - 1
    n = cursor.shape[0]
    strip_start[:] = 0
    for p in range(n):
        strip_start[cursor[p] + 1] += 1
    for s in range(ns):
        strip_start[s + 1] += strip_start[s]
    fill = strip_start[:ns].copy()
    for p in range(n):
        s = cursor[p]
        order[fill[s]] = p
        fill[s] += 1


@njit(cache=True, error_model="numpy")
def sort_into_strips(py, gp, strip_start, cursor, order):
    """Strip of every point and the stable counting sort (``strip_index`` + ``counting_sort``)."""
    strip_index(py, gp, cursor, strip_start.shape[0] - 1)
    counting_sort(cursor, strip_start, order)


@njit(cache=True, error_model="numpy", inline="always")
def _scatter_point(p, x, v, C, mass, vol0, J, sig, pres, grid, h, x0, y0, nx, periodic, force):
    """P2G of one point onto its 3 × 3 nodes: mass, APIC momentum, internal force, m p and m ρ."""
    xp = x[0, p]
    yp = x[1, p]
    bx, wx0, wx1, wx2, dx0, dx1, dx2 = bspline2((xp - x0) / h)
    by, wy0, wy1, wy2, dy0, dy1, dy2 = bspline2((yp - y0) / h)
    m = mass[p]
    vol = vol0[p] * J[p]
    rho = m / vol
    vx = v[0, p]
    vy = v[1, p]
    c00 = C[0, p]
    c01 = C[1, p]
    c10 = C[2, p]
    c11 = C[3, p]
    # −V σ·∇w with ∇w per grid unit: the 1/h is folded into the stress
    fv = -vol / h
    sxx = fv * sig[0, p]
    syy = fv * sig[1, p]
    sxy = fv * sig[2, p]
    pp = pres[p]
    for a in range(3):
        wa = wx0 if a == 0 else (wx1 if a == 1 else wx2)
        da = dx0 if a == 0 else (dx1 if a == 1 else dx2)
        ixu = bx + a
        ix = _wrap(ixu, nx) if periodic else ixu
        ddx = ixu * h + x0 - xp
        mvx = vx + c00 * ddx
        mvy = vy + c10 * ddx
        for b in range(3):
            wb = wy0 if b == 0 else (wy1 if b == 1 else wy2)
            iy = by + b
            ddy = iy * h + y0 - yp
            mw = m * (wa * wb)
            grid[ix, iy, N_MASS] += mw
            grid[ix, iy, N_MX] += mw * (mvx + c01 * ddy)
            grid[ix, iy, N_MY] += mw * (mvy + c11 * ddy)
            grid[ix, iy, N_MP] += mw * pp
            grid[ix, iy, N_MRHO] += mw * rho
            if force:
                db = dy0 if b == 0 else (dy1 if b == 1 else dy2)
                gx = da * wb
                gy = wa * db
                grid[ix, iy, N_FX] += sxx * gx + sxy * gy
                grid[ix, iy, N_FY] += sxy * gx + syy * gy


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


@njit(cache=True, error_model="numpy", parallel=True)
def p2g(x, v, C, mass, vol0, J, sig, pres, gp, grid, strip_start, order, bounds, with_force):
    """Scatter mass, APIC momentum, internal force −Σ V σ·∇w, and the mass-weighted p and ρ.

    ``bounds`` (threads + 1): work array; its length sets the number of balanced strip runs."""
    grid[:] = 0.0
    ns = strip_start.shape[0] - 1
    h = gp[G_H]
    x0 = gp[G_X0]
    y0 = gp[G_Y0]
    nx = int(gp[G_NX])
    periodic = gp[G_PERIODIC] != 0.0
    nt = bounds.shape[0] - 1
    for colour in range(2):
        nc = (ns - colour + 1) // 2
        _balance(strip_start, colour, nc, bounds)
        for t in prange(nt):
            for k in range(bounds[t], bounds[t + 1]):
                s = colour + 2 * k
                for i in range(strip_start[s], strip_start[s + 1]):
                    _scatter_point(order[i], x, v, C, mass, vol0, J, sig, pres, grid,
                                   h, x0, y0, nx, periodic, with_force)  # fmt: skip


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
    grid[im, jm, N_MP] += grid[ig, jg, N_MP]
    grid[im, jm, N_MRHO] += grid[ig, jg, N_MRHO]
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
    """Nodal velocities behind no-slip walls: minus those of their mirror nodes (``fold_images``)."""
    for r in range(pairs.shape[0]):
        ig, jg, im, jm = pairs[r, 0], pairs[r, 1], pairs[r, 2], pairs[r, 3]
        gv[ig, jg, 0] = -gv[im, jm, 0]
        gv[ig, jg, 1] = -gv[im, jm, 1]


@njit(cache=True, error_model="numpy", parallel=True)
def grid_update(gp, grid, gv, gv_old, dt, ramp, sidewall_on):
    """Nodal velocities: v* = (m v + Δt (f + m g))/m, sidewall friction, then boundaries.

    ``ramp`` ∈ [0, 1] scales the tangential gravity and the sidewall force (start-up ramp).
    ``gv_old`` receives m v / m before the update, with the same boundary conditions (FLIP).
    """
    nx = grid.shape[0]
    ny = grid.shape[1]
    h = gp[G_H]
    x0 = gp[G_X0]
    y0 = gp[G_Y0]
    gx = gp[G_GX] * ramp
    gy = gp[G_GY]
    sw = gp[G_SIDEWALL] * ramp
    for i in prange(nx):
        xn = x0 + i * h
        for j in range(ny):
            m = grid[i, j, N_MASS]
            if m <= 0.0:
                gv[i, j, 0] = 0.0
                gv[i, j, 1] = 0.0
                gv_old[i, j, 0] = 0.0
                gv_old[i, j, 1] = 0.0
                continue
            vox = grid[i, j, N_MX] / m
            voy = grid[i, j, N_MY] / m
            vx = vox + dt * (grid[i, j, N_FX] / m + gx)
            vy = voy + dt * (grid[i, j, N_FY] / m + gy)
            if sidewall_on and sw > 0.0:
                pn = grid[i, j, N_MP] / m
                if pn > 0.0:
                    rn = grid[i, j, N_MRHO] / m
                    vx, vy = sidewall_friction(vx, vy, dt * sw * pn / rn)
            yn = y0 + j * h
            vx, vy = apply_bc(gp, xn, yn, vx, vy)
            # the boundary also constrains the old velocity, so that the FLIP increment on a
            # constrained node is only the physical change: otherwise zeroing a node's projected
            # velocity every step would act as a drag ∝ 1/Δt on the points near the wall
            vox, voy = apply_bc(gp, xn, yn, vox, voy)
            gv[i, j, 0] = vx
            gv[i, j, 1] = vy
            gv_old[i, j, 0] = vox
            gv_old[i, j, 1] = voy


@njit(cache=True, error_model="numpy", parallel=True)
def momentum_to_velocity(gp, grid, gv):
    """MUSL remap: nodal velocity from the re-scattered point momenta, with the boundaries."""
    nx = grid.shape[0]
    ny = grid.shape[1]
    h = gp[G_H]
    for i in prange(nx):
        for j in range(ny):
            m = grid[i, j, N_MASS]
            if m <= 0.0:
                gv[i, j, 0] = 0.0
                gv[i, j, 1] = 0.0
                continue
            vx, vy = apply_bc(
                gp, gp[G_X0] + i * h, gp[G_Y0] + j * h, grid[i, j, N_MX] / m, grid[i, j, N_MY] / m
            )
            gv[i, j, 0] = vx
            gv[i, j, 1] = vy


@njit(cache=True, error_model="numpy", inline="always")
def gather(px, py, gv, gv_old, h, x0, y0, nx, periodic, old):
    """G2P at (px, py) in one pass over the 3 × 3 nodes: Σ w v_i, the APIC matrix
    C_p = (4/h²) Σ w v_i (x_i − x_p)ᵀ, L_p = Σ v_i ⊗ ∇w_i, and (if ``old``) Σ w v_i^old, the old
    nodal velocity of the FLIP increment. Returns (vx, vy, C00, C01, C10, C11, L00, L01, L10, L11,
    ox, oy)."""
    bx, wx0, wx1, wx2, dx0, dx1, dx2 = bspline2((px - x0) / h)
    by, wy0, wy1, wy2, dy0, dy1, dy2 = bspline2((py - y0) / h)
    vx = 0.0
    vy = 0.0
    b00 = 0.0
    b01 = 0.0
    b10 = 0.0
    b11 = 0.0
    l00 = 0.0
    l01 = 0.0
    l10 = 0.0
    l11 = 0.0
    ox = 0.0
    oy = 0.0
    for a in range(3):
        wa = wx0 if a == 0 else (wx1 if a == 1 else wx2)
        da = dx0 if a == 0 else (dx1 if a == 1 else dx2)
        ixu = bx + a
        ix = _wrap(ixu, nx) if periodic else ixu
        ddx = ixu * h + x0 - px
        for b in range(3):
            wb = wy0 if b == 0 else (wy1 if b == 1 else wy2)
            db = dy0 if b == 0 else (dy1 if b == 1 else dy2)
            iy = by + b
            ddy = iy * h + y0 - py
            w = wa * wb
            ux = gv[ix, iy, 0]
            uy = gv[ix, iy, 1]
            wux = w * ux
            wuy = w * uy
            vx += wux
            vy += wuy
            b00 += wux * ddx
            b01 += wux * ddy
            b10 += wuy * ddx
            b11 += wuy * ddy
            gxw = da * wb
            gyw = wa * db
            l00 += ux * gxw
            l01 += ux * gyw
            l10 += uy * gxw
            l11 += uy * gyw
            if old:
                ox += w * gv_old[ix, iy, 0]
                oy += w * gv_old[ix, iy, 1]
    k = 4.0 / (h * h)
    r = 1.0 / h
    return (vx, vy, k * b00, k * b01, k * b10, k * b11, r * l00, r * l01, r * l10, r * l11, ox, oy)
