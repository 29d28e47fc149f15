"""Dimension-generic MPM kernels: the one source of the 2-D and the 3-D engine.

This file is a *template*. :mod:`segmpm.engine.codegen` writes it out once per dimension with the
line ``D = 2`` set to the dimension (files ``kernels_d2.py`` and ``kernels_d3.py`` in the keyed
kernel cache, so that Numba's ``cache=True`` works on them), and imports the copy; the last
section (the material pass and the time loop, from ``STEP_SECTION``) goes to a file per law
with ``LAW`` set, so that a run compiles only its own law. ``D`` is then
a compile-time constant: every ``if D == 3`` is pruned, the z stencil of 2-D is one node of
weight 1, and the zero out-of-plane components of the tensors fold away. The physics is written
once, in full 3-D tensor form; 2-D plane strain is the special case with no z velocity.

Order of a step (:func:`advance`, docs/architecture.md):

1. sort the points into slabs of ``SLAB`` cell layers in y (P2G without atomics, deterministic);
2. P2G: mass, APIC momentum, internal force −Σ V σ ∇w, Σ w V p; the sums of the nodes behind
   a wall folded onto their mirror nodes (image nodes);
3. grid update: v* = (m v + Δt (f + m g))/m, the 2-D sidewall body force, the boundary planes;
   and the image nodes' velocities from their mirrors;
4. G2P: APIC/AFLIP velocity, affine matrix C, velocity gradient L, advection, J; with MUSL
   (``grid.transfer = "flip"``) the updated momenta are scattered again from the old positions
   and L is taken there; with the volumetric smoothing, tr L mapped to the grid and back
   before J;
5. material law (Fei et al. 2016, Jiang–Liu elasticity + yield cap + μ(I), or the fluidity flow
   rule of the nonlocal rheology) and the step check; with the nonlocal rheology, every
   ``material.fluidity_dt`` the fluidity update (diffusion on the grid, local relaxation);
6. every segregation subcycle, the concentration step on the extra Eulerian grid.

Points, grid and parameters are the named records of :mod:`segmpm.engine.records`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from segmpm import _llvm_options  # noqa: F401  (before any kernel compiles)
from segmpm._fmath import flog, fsqrt
from segmpm.engine.helpers import (
    B_BAD,
    B_GDOT,
    B_I,
    B_NU,
    B_ROWS,
    B_S,
    B_SPEED,
    CAPACITY_MIN,
    FILL_OFFSET,
    FILL_SLOPE,
    PIC,
    SAFETY,
    TINY,
    _balance,
    _reduce_block,
    counting_sort,
    node_velocity,
    sidewall_drag,
)
from segmpm.engine.records import (
    BC_FRICTION,
    BC_NOSLIP,
    BC_OPEN,
    BC_SLIP,
    BC_SYMMETRY,
    COL_U,
    COL_V,
    COL_Y,
    XY,
    YY,
)
from segmpm.engine.shape import bspline2_frac
from segmpm.materials import VAR_ELASTIC, VAR_FEI_LINEAR, VAR_FEI_POWER, VAR_NGF
from segmpm.materials.ngf import relax_logistic, return_factor
from segmpm.materials.params import (
    DRIVER_A,
    DRIVER_B,
    DRIVER_C,
    DRIVER_P,
    KIND_FEI2016,
    KIND_FEI2016_NGF,
)
from segmpm.mpm.params import (
    ST_DT_COLLAPSE,
    ST_LEFT_GRID,
    ST_NONFINITE,
    ST_OK,
    TRANSFER_AFLIP,
    TRANSFER_FLIP,
)
from segmpm.segregation.closures import (
    M_NONE,
    P_D_LARGE,
    P_D_SMALL,
    P_DT_TARGET,
    P_FILL_MIN,
    P_FLUX,
    P_MODEL,
    P_SAFETY,
    face_rates,
    face_velocity_diffusivity,
)
from segmpm.segregation.grid import tent_weights

#: the dimension of this copy (set by the code generator)
D = 2

#: stencil nodes along z: three in 3-D, one of weight 1 in 2-D
SZ = 3 if D == 3 else 1
#: stored components of a symmetric tensor: xx, yy, zz, xy and, in 3-D, xz, yz
NE = 6 if D == 3 else 4
#: nodal P2G fields: mass, momentum (D), force (D) and, in 2-D, Σ w V p (the pressure integral
#: of the sidewall body force; 3-D resolves the walls)
F_M = 0
F_P = 1
F_F = 1 + D
F_VP = 1 + 2 * D
NF = 2 + 2 * D if D == 2 else 1 + 2 * D
#: nodal velocity lanes: the updated velocity v* (D) and the old velocity m v / m (D)
V_NEW = 0
V_OLD = D
NV = 2 * D
#: cell layers (in y) per P2G slab: a point touches 3 node layers, so slabs two apart share none
SLAB = 3


# ---------------------------------------------------------------------------------------------
# small helpers: a point's vector and tensors as full 3-D tuples (zeros out of plane in 2-D)


@njit(cache=True, error_model="numpy", inline="always")
def _vec(a, p):
    """Column p of a (D, N) array as (x, y, z)."""
    if D == 3:
        return a[0, p], a[1, p], a[2, p]
    return a[0, p], a[1, p], 0.0


@njit(cache=True, error_model="numpy", inline="always")
def _mat(a, p):
    """Row-major D×D matrix of point p (a (D·D, N) array) as a full 3×3, row-major."""
    if D == 3:
        return (a[0, p], a[1, p], a[2, p], a[3, p], a[4, p], a[5, p], a[6, p], a[7, p],
                a[8, p])  # fmt: skip
    return a[0, p], a[1, p], 0.0, a[2, p], a[3, p], 0.0, 0.0, 0.0, 0.0


@njit(cache=True, error_model="numpy", inline="always")
def _sym(a, p):
    """Symmetric tensor of point p as (xx, yy, zz, xy, xz, yz)."""
    if D == 3:
        return a[0, p], a[1, p], a[2, p], a[3, p], a[4, p], a[5, p]
    return a[0, p], a[1, p], a[2, p], a[3, p], 0.0, 0.0


@njit(cache=True, error_model="numpy", inline="always")
def _put_sym(a, p, xx, yy, zz, xy, xz, yz):
    a[0, p] = xx
    a[1, p] = yy
    a[2, p] = zz
    a[3, p] = xy
    if D == 3:
        a[4, p] = xz
        a[5, p] = yz


@njit(cache=True, error_model="numpy", inline="always")
def _put_mat3(a, p, xx, xy, xz, yx, yy, yz, zx, zy, zz):
    """Store a row-major 3×3 matrix as column p of a (9, N) array."""
    a[0, p] = xx
    a[1, p] = xy
    a[2, p] = xz
    a[3, p] = yx
    a[4, p] = yy
    a[5, p] = yz
    a[6, p] = zx
    a[7, p] = zy
    a[8, p] = zz


@njit(cache=True, error_model="numpy", inline="always")
def _wrap(i, n):
    """Periodic node index for i in [−n, 2n)."""
    if i < 0:
        return i + n
    if i >= n:
        return i - n
    return i


@njit(cache=True, error_model="numpy", inline="always")
def _nz(n):
    """The node count along z as the loops and flat indices see it: ``n`` in 3-D, a compile-time
    1 in 2-D, so that the z loops and the z terms of the indices fold away."""
    if D == 3:
        return n
    return 1


@njit(cache=True, error_model="numpy", inline="always")
def _z_axis(z, z0, ih):
    """The z factor of the stencil: B-spline in 3-D; one node of weight 1 in 2-D."""
    if D == 3:
        return bspline2_frac((z - z0) * ih)
    return 0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0


# ---------------------------------------------------------------------------------------------
# 1. slabs of the P2G sort


@njit(cache=True, error_model="numpy", inline="always")
def slab_of(y, y0, ih, nslabs):
    """P2G slab of a point at height y, clamped to [0, nslabs)."""
    s = int(math.floor((y - y0) * ih)) // SLAB
    return min(max(s, 0), nslabs - 1)


@njit(cache=True, error_model="numpy", parallel=True)
def slab_index(P, prm, nslabs):
    """``P.cursor[p]``: the slab of every point."""
    ih = 1.0 / prm[0].h
    y0 = prm[0].origin[1]
    x = P.x
    cursor = P.cursor
    for p in prange(x.shape[1]):
        cursor[p] = slab_of(x[1, p], y0, ih, nslabs)


# ---------------------------------------------------------------------------------------------
# 2. P2G


#: the nodal P2G fields as unsigned offsets (unsigned indices: no negative-index wrap)
U_M = np.uint64(F_M)
U_P = np.uint64(F_P)
U_P1 = np.uint64(F_P + 1)
U_P2 = np.uint64(F_P + 2)
U_F = np.uint64(F_F)
U_F1 = np.uint64(F_F + 1)
U_F2 = np.uint64(F_F + 2)
U_VP = np.uint64(F_VP)
U_NF = np.uint64(NF)


@njit(cache=True, error_model="numpy", inline="always")
def _scatter_x(g, kx, sy, ex, wxa, dxa, wy, dy, fy, wz, dz, fz, h, m, vp, vel, cm, s6,
               with_force):  # fmt: skip
    """P2G onto the 3 × 3 (y, z) nodes of one x index of the stencil (``kx`` the lanes of node
    (i, b_y, b_z), ``sy`` the lane stride along y; ``ex`` = x_i − x_p, ``wxa``, ``dxa`` the x
    factors of w and ∇w; ``wy`` … ``dz`` the y and z factors as triples; ``vel``, ``cm``, ``s6``
    the point's v, C and −V σ/h)."""
    vx, vy, vz = vel
    cxx, cxy, cxz, cyx, cyy, cyz, czx, czy, czz = cm
    sxx, syy, szz, sxy, sxz, syz = s6
    # the x part of the affine velocity
    ax = vx + cxx * ex
    ay = vy + cyx * ex
    az = vz + czx * ex
    for b in range(3):
        ey = (b - fy) * h
        wab = wxa * wy[b]
        ga = dxa * wy[b]
        gb = wxa * dy[b]
        # per column: the in-plane part of the affine velocity and of σ·∇w
        mx = ax + cxy * ey
        my = ay + cyy * ey
        mz = az + czy * ey
        tx = sxx * ga + sxy * gb
        ty = sxy * ga + syy * gb
        tz = sxz * ga + syz * gb
        k0 = kx + np.uint64(b) * sy
        for c in range(SZ):
            k = k0 + np.uint64(c) * U_NF
            wc = wz[c]
            mw = m * wab * wc
            g[k + U_M] += mw
            if D == 3:
                ez = (c - fz) * h
                g[k + U_P] += mw * (mx + cxz * ez)
                g[k + U_P1] += mw * (my + cyz * ez)
                g[k + U_P2] += mw * (mz + czz * ez)
            else:
                g[k + U_P] += mw * mx
                g[k + U_P1] += mw * my
            if with_force:
                if D == 3:
                    dc = dz[c] * wab
                    g[k + U_F] += wc * tx + dc * sxz
                    g[k + U_F1] += wc * ty + dc * syz
                    g[k + U_F2] += wc * tz + dc * szz
                else:
                    g[k + U_F] += tx
                    g[k + U_F1] += ty
            if D == 2:
                g[k + U_VP] += wab * vp


@njit(cache=True, error_model="numpy", inline="always")
def _scatter_point(p, x, v, C, mass, vol0, J, sig, pres, g, h, ih, x0, y0, z0, nx, ny, nz,
                   periodic, with_force):  # fmt: skip
    """P2G of point p onto its 3 × 3 (× 3) nodes (``g``: the flat nodal array), one x index of
    the stencil at a time (written out: a loop over them stays a loop, with its factors in
    memory)."""
    bx, wx0, wx1, wx2, dx0, dx1, dx2, fx = bspline2_frac((x[0, p] - x0) * ih)
    by, wy0, wy1, wy2, dy0, dy1, dy2, fy = bspline2_frac((x[1, p] - y0) * ih)
    zp = x[2, p] if D == 3 else 0.0
    bz, wz0, wz1, wz2, dz0, dz1, dz2, fz = _z_axis(zp, z0, ih)
    wy = (wy0, wy1, wy2)
    dy = (dy0, dy1, dy2)
    wz = (wz0, wz1, wz2)
    dz = (dz0, dz1, dz2)
    m = mass[p]
    vol = vol0[p] * J[p]
    # −V σ·∇w with ∇w per grid unit: −V/h is folded into the stress
    fv = -vol * ih
    sxx, syy, szz, sxy, sxz, syz = _sym(sig, p)
    s6 = (sxx * fv, syy * fv, szz * fv, sxy * fv, sxz * fv, syz * fv)
    vp = vol * pres[p]
    vel = _vec(v, p)
    cm = _mat(C, p)
    i0 = bx
    i1 = bx + 1
    i2 = bx + 2
    if periodic:
        i0 = _wrap(i0, nx)
        i1 = _wrap(i1, nx)
        i2 = _wrap(i2, nx)
    sy = np.uint64(nz * NF)
    _scatter_x(g, np.uint64(((i0 * ny + by) * nz + bz) * NF), sy, -fx * h, wx0, dx0, wy, dy, fy,
               wz, dz, fz, h, m, vp, vel, cm, s6, with_force)  # fmt: skip
    _scatter_x(g, np.uint64(((i1 * ny + by) * nz + bz) * NF), sy, (1.0 - fx) * h, wx1, dx1, wy,
               dy, fy, wz, dz, fz, h, m, vp, vel, cm, s6, with_force)  # fmt: skip
    _scatter_x(g, np.uint64(((i2 * ny + by) * nz + bz) * NF), sy, (2.0 - fx) * h, wx2, dx2, wy,
               dy, fy, wz, dz, fz, h, m, vp, vel, cm, s6, with_force)  # fmt: skip


@njit(cache=True, error_model="numpy", parallel=True, fastmath={"contract"})
def p2g(P, G, prm, remap):
    """Scatter mass, APIC momentum m(v + C(x_i − x_p)), internal force −Σ V σ·∇w and Σ w V p.
    ``remap`` (MUSL): mass and momentum only, at the positions before G2P (``P.x_old``).

    Slabs of one colour (even, then odd) scatter concurrently, each its points in index order:
    every node receives its contributions in the same order on any number of threads."""
    g = G.nodes.reshape(G.nodes.size)
    g[:] = 0.0
    ns = G.slab_start.shape[0] - 1
    ny = G.nodes.shape[1]
    nz = _nz(G.nodes.shape[2])
    nt = G.bounds.shape[0] - 1
    if remap and P.x_old.shape[1] != P.x.shape[1]:
        raise ValueError("p2g(remap=True) needs P.x_old for every point (grid.transfer = 'flip')")
    with_force = not remap
    x = P.x_old if remap else P.x
    v = P.v
    C = P.C
    mass = P.mass
    vol0 = P.vol0
    J = P.J
    sig = P.sig
    pres = P.diag[0]
    order = G.order
    bounds = G.bounds
    slab_start = G.slab_start
    pr = prm[0]
    h = pr.h
    ih = 1.0 / h
    x0 = pr.origin[0]
    y0 = pr.origin[1]
    z0 = pr.origin[2]
    nx = pr.nodes[0]
    periodic = pr.periodic_x != 0
    for colour in range(2):
        nc = (ns - colour + 1) // 2
        _balance(slab_start, colour, nc, bounds)
        for t in prange(nt):
            for k in range(bounds[t], bounds[t + 1]):
                s = colour + 2 * k
                for q in range(slab_start[s], slab_start[s + 1]):
                    _scatter_point(order[q], x, v, C, mass, vol0, J, sig, pres, g, h, ih, x0,
                                   y0, z0, nx, ny, nz, periodic, with_force)  # fmt: skip


# ---------------------------------------------------------------------------------------------
# 2b. image nodes behind walls that lie on a node plane


@njit(cache=True, error_model="numpy", inline="always")
def _plane_node(coord, origin, h, n):
    """Index of the node plane at ``coord`` if it is one (not the first or last), else −1."""
    r = (coord - origin) / h
    k = int(math.floor(r + 0.5))
    if abs(r - k) > 1e-6 or k < 1 or k > n - 2:
        return -1
    return k


@njit(cache=True, error_model="numpy")
def image_planes(prm):
    """The walls that get image nodes, rows (axis, node index of the plane, side −1 below /
    +1 above, 1 if no-slip): the base, then x = xlo, xhi (non-periodic), then z = zlo, zhi (3-D).
    Behind a no-slip wall the velocity is extended oddly (it vanishes on the wall); behind a
    slip or symmetry plane the tangential velocity evenly and the normal one oddly (the mirror
    image of the material). A Coulomb wall gets none: its friction is bounded by the normal
    impulse of the wall nodes, and an image would carry part of the normal reaction past them
    (tests/test_engine.py, the sliding block). Only with ``prm.images``."""
    pr = prm[0]
    out = np.full((5, 4), -1, dtype=np.int64)
    if pr.images == 0:
        return out[:0]
    h = pr.h
    r = 0
    kinds = (pr.base_kind, pr.xlo_kind, pr.xhi_kind, pr.zlo_kind, pr.zhi_kind)
    where = (pr.base_y, pr.xlo, pr.xhi, pr.zlo, pr.zhi)
    axes = (1, 0, 0, 2, 2)
    sides = (-1, -1, 1, -1, 1)
    for q in range(5):
        a = axes[q]
        if kinds[q] == BC_OPEN or kinds[q] == BC_FRICTION:
            continue
        if (a == 0 and pr.periodic_x != 0) or (a == 2 and D != 3):
            continue
        k = _plane_node(where[q], pr.origin[a], h, pr.nodes[a])
        if k < 0:
            continue
        out[r, 0] = a
        out[r, 1] = k
        out[r, 2] = sides[q]
        out[r, 3] = 1 if kinds[q] == BC_NOSLIP else 0
        r += 1
    return out[:r]


@njit(cache=True, error_model="numpy", inline="always")
def _mirror_index(i, j, k, axis, kw, side):
    """The mirror of node (i, j, k) across the plane ``kw`` of ``axis``, or −1 if the node is
    not behind the plane (``side`` −1: behind means below)."""
    c = i if axis == 0 else (j if axis == 1 else k)
    if (side < 0 and c >= kw) or (side > 0 and c <= kw):
        return -1
    return 2 * kw - c


@njit(cache=True, error_model="numpy", inline="always")
def _behind(axis, kw, side, nx, ny, nz):
    """Index ranges (i, j, k: lo, hi) of the nodes behind the plane ``kw`` of ``axis``."""
    n = nx if axis == 0 else (ny if axis == 1 else nz)
    lo = 0 if side < 0 else kw + 1
    hi = kw if side < 0 else n
    return ((lo, hi) if axis == 0 else (0, nx), (lo, hi) if axis == 1 else (0, ny),
            (lo, hi) if axis == 2 else (0, nz))  # fmt: skip


@njit(cache=True, error_model="numpy")
def fold_images(G, planes, prm, ramp):
    """The P2G sums of a node behind a wall folded onto its mirror node (mass +, each momentum
    and force component with the parity of the velocity's extension; docs/model.md, "No-slip
    walls"), so that the Galerkin system is that of the extended velocity field. ``ramp``
    scales the tangential gravity as in the grid update."""
    nodes = G.nodes
    nx, ny, nz = nodes.shape[0], nodes.shape[1], nodes.shape[2]
    pr = prm[0]
    grav = (pr.gravity[0] * ramp, pr.gravity[1], pr.gravity[2])
    for r in range(planes.shape[0]):
        axis, kw, side, noslip = planes[r, 0], planes[r, 1], planes[r, 2], planes[r, 3]
        ri, rj, rk = _behind(axis, kw, side, nx, ny, nz)
        for i in range(ri[0], ri[1]):
            for j in range(rj[0], rj[1]):
                for k in range(rk[0], rk[1]):
                    mi = _mirror_index(i, j, k, axis, kw, side)
                    if mi < 0:
                        continue
                    im, jm, km = i, j, k
                    if axis == 0:
                        im = mi
                    elif axis == 1:
                        jm = mi
                    else:
                        km = mi
                    if im < 0 or im >= nx or jm < 0 or jm >= ny or km < 0 or km >= nz:
                        continue
                    src = nodes[i, j, k]
                    dst = nodes[im, jm, km]
                    m = src[F_M]
                    dst[F_M] += m
                    for a in range(D):
                        odd = noslip == 1 or a == axis
                        if odd:
                            # the odd image of m g on the node behind, and the m g the mirror
                            # node gets for this mass afterwards
                            dst[F_P + a] -= src[F_P + a]
                            dst[F_F + a] -= src[F_F + a] + 2.0 * m * grav[a]
                        else:
                            dst[F_P + a] += src[F_P + a]
                            dst[F_F + a] += src[F_F + a]
                    if D == 2:
                        dst[F_VP] += src[F_VP]
                    src[:] = 0.0


@njit(cache=True, error_model="numpy")
def mirror_images(G, planes):
    """Nodal velocities behind the walls: those of their mirror nodes, with the parity of
    ``fold_images`` (every lane)."""
    gv = G.gv
    nx, ny, nz = gv.shape[0], gv.shape[1], gv.shape[2]
    for r in range(planes.shape[0]):
        axis, kw, side, noslip = planes[r, 0], planes[r, 1], planes[r, 2], planes[r, 3]
        ri, rj, rk = _behind(axis, kw, side, nx, ny, nz)
        for i in range(ri[0], ri[1]):
            for j in range(rj[0], rj[1]):
                for k in range(rk[0], rk[1]):
                    mi = _mirror_index(i, j, k, axis, kw, side)
                    if mi < 0:
                        continue
                    im, jm, km = i, j, k
                    if axis == 0:
                        im = mi
                    elif axis == 1:
                        jm = mi
                    else:
                        km = mi
                    if im < 0 or im >= nx or jm < 0 or jm >= ny or km < 0 or km >= nz:
                        im, jm, km = (kw if axis == 0 else i, kw if axis == 1 else j,
                                      kw if axis == 2 else k)  # fmt: skip
                    for a in range(D):
                        sgn = -1.0 if (noslip == 1 or a == axis) else 1.0
                        gv[i, j, k, V_NEW + a] = sgn * gv[im, jm, km, V_NEW + a]
                        gv[i, j, k, V_OLD + a] = sgn * gv[im, jm, km, V_OLD + a]


# ---------------------------------------------------------------------------------------------
# 3. grid update and boundary planes


@njit(cache=True, error_model="numpy", inline="always")
def _plane(kind, mu, mu0, uw, vn, t1, t2):
    """A wall in its own frame (vn > 0 points away from the wall into the material): no-slip,
    symmetry (vn = 0), free slip or Coulomb friction (the tangential impulse at most μ times the
    normal one; Bardenhagen, Brackbill & Sulsky 2000); slip and friction let the material leave.
    With u_w > 0 the friction grows with the (trial) sliding speed u, μ(u) = μ₀ + (μ − μ₀)
    u/(u + u_w) (the wall law measured at a flat wall, docs/calibration.md)."""
    if kind == BC_NOSLIP:
        return 0.0, 0.0, 0.0
    if kind == BC_SYMMETRY:
        return 0.0, t1, t2
    if vn >= 0.0:
        return vn, t1, t2
    if kind == BC_SLIP:
        return 0.0, t1, t2
    dvn = -vn
    at = math.sqrt(t1 * t1 + t2 * t2)
    if uw > 0.0:
        mu = mu0 + (mu - mu0) * at / (at + uw)
    if at <= mu * dvn:
        return 0.0, 0.0, 0.0
    s = 1.0 - mu * dvn / at
    return 0.0, t1 * s, t2 * s


@njit(cache=True, error_model="numpy", inline="always")
def apply_planes(prm, xn, yn, zn, vx, vy, vz):
    """The velocity of the node at (xn, yn, zn) after the boundary planes (nodes at and beyond a
    plane): the base y = base_y, the walls x = xlo, xhi (non-periodic x), z = zlo, zhi (3-D;
    their friction may depend on the sliding speed, ``wall_mu0``, ``wall_speed``)."""
    pr = prm[0]
    tol = 1e-9 * pr.h
    if pr.base_kind != BC_OPEN and yn <= pr.base_y + tol:
        vy, vx, vz = _plane(pr.base_kind, pr.base_mu, pr.base_mu, 0.0, vy, vx, vz)
    if pr.periodic_x == 0:
        if pr.xlo_kind != BC_OPEN and xn <= pr.xlo + tol:
            vx, vy, vz = _plane(pr.xlo_kind, pr.xlo_mu, pr.xlo_mu, 0.0, vx, vy, vz)
        if pr.xhi_kind != BC_OPEN and xn >= pr.xhi - tol:
            nvx, vy, vz = _plane(pr.xhi_kind, pr.xhi_mu, pr.xhi_mu, 0.0, -vx, vy, vz)
            vx = -nvx
    if D == 3:
        uw = pr.wall_speed
        if pr.zlo_kind != BC_OPEN and zn <= pr.zlo + tol:
            vz, vx, vy = _plane(pr.zlo_kind, pr.zlo_mu, pr.wall_mu0, uw, vz, vx, vy)
        if pr.zhi_kind != BC_OPEN and zn >= pr.zhi - tol:
            nvz, vx, vy = _plane(pr.zhi_kind, pr.zhi_mu, pr.wall_mu0, uw, -vz, vx, vy)
            vz = -nvz
    return vx, vy, vz


@njit(cache=True, error_model="numpy", parallel=True)
def grid_update(G, prm, dt, ramp):
    """Nodal velocities v* = (m v + Δt (f + m g))/m, the 2-D sidewall Coulomb body force, then
    the boundary planes, on the new and (for AFLIP) the old velocity alike."""
    nx, ny, nz = G.nodes.shape[0], G.nodes.shape[1], _nz(G.nodes.shape[2])
    pr = prm[0]
    h = pr.h
    x0 = pr.origin[0]
    y0 = pr.origin[1]
    z0 = pr.origin[2]
    gx = pr.gravity[0] * ramp
    gy = pr.gravity[1]
    gz = pr.gravity[2]
    sw = pr.sidewall * ramp
    uw = pr.sidewall_speed
    sw0 = pr.sidewall_slow * ramp if uw > 0.0 else sw
    # the arrays out of the records before a parallel loop (docs/architecture.md), flat
    gf = G.nodes.reshape(G.nodes.size)
    gvf = G.gv.reshape(G.gv.size)
    for i in prange(nx):
        xn = x0 + i * h
        for j in range(ny):
            yn = y0 + j * h
            for k in range(nz):
                zn = z0 + k * h
                q = ((i * ny + j) * nz + k) * NF
                o = ((i * ny + j) * nz + k) * NV
                m = gf[q + F_M]
                if m <= 0.0:
                    for a in range(NV):
                        gvf[o + a] = 0.0
                    continue
                im = 1.0 / m
                ox = gf[q + F_P] * im
                oy = gf[q + F_P + 1] * im
                oz = gf[q + F_P + 2] * im if D == 3 else 0.0
                vx = ox + dt * (gf[q + F_F] * im + gx)
                vy = oy + dt * (gf[q + F_F + 1] * im + gy)
                vz = oz + dt * (gf[q + F_F + 2] * im + gz) if D == 3 else 0.0
                if D == 2 and (sw > 0.0 or sw0 > 0.0) and gf[q + F_VP] > 0.0:
                    vx, vy = sidewall_drag(vx, vy, sw, sw0, uw, dt, gf[q + F_VP], im)
                vx, vy, vz = apply_planes(prm, xn, yn, zn, vx, vy, vz)
                # the old velocity gets the same constraints: the FLIP increment on a
                # constrained node is then only the physical change
                ox, oy, oz = apply_planes(prm, xn, yn, zn, ox, oy, oz)
                gvf[o + V_NEW] = vx
                gvf[o + V_NEW + 1] = vy
                gvf[o + V_OLD] = ox
                gvf[o + V_OLD + 1] = oy
                if D == 3:
                    gvf[o + V_NEW + 2] = vz
                    gvf[o + V_OLD + 2] = oz


# ---------------------------------------------------------------------------------------------
# 4. G2P


#: the nodal velocity lanes as unsigned offsets (unsigned indices: no negative-index wrap)
U_NEW = np.uint64(V_NEW)
U_NEW1 = np.uint64(V_NEW + 1)
U_NEW2 = np.uint64(V_NEW + 2)
U_OLD = np.uint64(V_OLD)
U_OLD1 = np.uint64(V_OLD + 1)
U_OLD2 = np.uint64(V_OLD + 2)


@njit(cache=True, error_model="numpy", inline="always")
def _dot3(w, a, b, c):
    """w · (a, b, c) for a triple of stencil factors w."""
    return w[0] * a + w[1] * b + w[2] * c


@njit(cache=True, error_model="numpy", inline="always")
def _ycolumn(gvf, k, sy, wy, dy, ey):
    """Sums over the three nodes of one y column (``k`` the lanes of its lowest node, ``sy`` the
    lane stride along y): Σ w_y v, Σ w_y v_old, Σ w_y′ v and Σ e_y v (e_y = w_y (y_b − y_p)),
    each as an (x, y, z) triple with zeros out of plane in 2-D."""
    n0 = np.uint64(k)
    n1 = n0 + np.uint64(sy)
    n2 = n1 + np.uint64(sy)
    ax = gvf[n0 + U_NEW]
    bx = gvf[n1 + U_NEW]
    cx = gvf[n2 + U_NEW]
    ay = gvf[n0 + U_NEW1]
    by = gvf[n1 + U_NEW1]
    cy = gvf[n2 + U_NEW1]
    wox = _dot3(wy, gvf[n0 + U_OLD], gvf[n1 + U_OLD], gvf[n2 + U_OLD])
    woy = _dot3(wy, gvf[n0 + U_OLD1], gvf[n1 + U_OLD1], gvf[n2 + U_OLD1])
    if D == 3:
        az = gvf[n0 + U_NEW2]
        bz = gvf[n1 + U_NEW2]
        cz = gvf[n2 + U_NEW2]
        woz = _dot3(wy, gvf[n0 + U_OLD2], gvf[n1 + U_OLD2], gvf[n2 + U_OLD2])
        wvz = _dot3(wy, az, bz, cz)
        dvz = _dot3(dy, az, bz, cz)
        evz = _dot3(ey, az, bz, cz)
    else:
        woz = wvz = dvz = evz = 0.0
    return (_dot3(wy, ax, bx, cx), _dot3(wy, ay, by, cy), wvz,
            wox, woy, woz,
            _dot3(dy, ax, bx, cx), _dot3(dy, ay, by, cy), dvz,
            _dot3(ey, ax, bx, cx), _dot3(ey, ay, by, cy), evz)  # fmt: skip


@njit(cache=True, error_model="numpy", inline="always")
def _xplane(gvf, k, sy, wy, dy, ey, wz, dz, ez):
    """Sums over the 3 × 3 (y, z) nodes of one x index (``k`` the lanes of node (·, b_y, b_z);
    ``wy`` … ``ez`` the y and z factors as triples): Σ w_y w_z v (3), Σ w_y w_z v_old (3),
    Σ w_y′ w_z v (3), Σ e_y w_z v (3), Σ w_y w_z′ v (3), Σ w_y e_z v (3); the last six zero
    in 2-D (one z node of weight 1)."""
    if D == 3:
        a = _ycolumn(gvf, k, sy, wy, dy, ey)
        b = _ycolumn(gvf, k + NV, sy, wy, dy, ey)
        c = _ycolumn(gvf, k + 2 * NV, sy, wy, dy, ey)
        return (_dot3(wz, a[0], b[0], c[0]), _dot3(wz, a[1], b[1], c[1]),
                _dot3(wz, a[2], b[2], c[2]), _dot3(wz, a[3], b[3], c[3]),
                _dot3(wz, a[4], b[4], c[4]), _dot3(wz, a[5], b[5], c[5]),
                _dot3(wz, a[6], b[6], c[6]), _dot3(wz, a[7], b[7], c[7]),
                _dot3(wz, a[8], b[8], c[8]), _dot3(wz, a[9], b[9], c[9]),
                _dot3(wz, a[10], b[10], c[10]), _dot3(wz, a[11], b[11], c[11]),
                _dot3(dz, a[0], b[0], c[0]), _dot3(dz, a[1], b[1], c[1]),
                _dot3(dz, a[2], b[2], c[2]), _dot3(ez, a[0], b[0], c[0]),
                _dot3(ez, a[1], b[1], c[1]), _dot3(ez, a[2], b[2], c[2]))  # fmt: skip
    a = _ycolumn(gvf, k, sy, wy, dy, ey)
    return (a[0], a[1], 0.0, a[3], a[4], 0.0, a[6], a[7], 0.0, a[9], a[10], 0.0,
            0.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # fmt: skip


@njit(cache=True, error_model="numpy", inline="always")
def gather(px, py, pz, gvf, h, ih, x0, y0, z0, nx, ny, nz, periodic):
    """The stencil sums of the point at (px, py, pz): Σ w v (new, old), B = Σ w v (x_i − x_p)ᵀ
    and L = Σ v ⊗ ∇w, as full 3-D tuples (row-major matrices; zeros out of plane in 2-D).
    Separably, with the weights w = w_x w_y w_z: sums along the y columns first, then along z
    (3-D), then across x; unsigned node offsets."""
    bx, wx0, wx1, wx2, dx0, dx1, dx2, fx = bspline2_frac((px - x0) * ih)
    by, wy0, wy1, wy2, dy0, dy1, dy2, fy = bspline2_frac((py - y0) * ih)
    bz, wz0, wz1, wz2, dz0, dz1, dz2, fz = _z_axis(pz, z0, ih)
    # w (x_i − x_p) along each axis: node a of the stencil lies at (a − f) h
    ex = (-fx * h * wx0, (1.0 - fx) * h * wx1, (2.0 - fx) * h * wx2)
    ey = (-fy * h * wy0, (1.0 - fy) * h * wy1, (2.0 - fy) * h * wy2)
    ez = (-fz * h * wz0, (1.0 - fz) * h * wz1, (2.0 - fz) * h * wz2)
    wy = (wy0, wy1, wy2)
    dy = (dy0, dy1, dy2)
    wz = (wz0, wz1, wz2)
    dz = (dz0, dz1, dz2)
    i0 = bx
    i1 = bx + 1
    i2 = bx + 2
    if periodic:
        i0 = _wrap(i0, nx)
        i1 = _wrap(i1, nx)
        i2 = _wrap(i2, nx)
    sy = nz * NV
    a = _xplane(gvf, ((i0 * ny + by) * nz + bz) * NV, sy, wy, dy, ey, wz, dz, ez)
    b = _xplane(gvf, ((i1 * ny + by) * nz + bz) * NV, sy, wy, dy, ey, wz, dz, ez)
    c = _xplane(gvf, ((i2 * ny + by) * nz + bz) * NV, sy, wy, dy, ey, wz, dz, ez)
    wx = (wx0, wx1, wx2)
    dx = (dx0, dx1, dx2)
    ux = _dot3(wx, a[0], b[0], c[0])
    uy = _dot3(wx, a[1], b[1], c[1])
    ox = _dot3(wx, a[3], b[3], c[3])
    oy = _dot3(wx, a[4], b[4], c[4])
    # B row-major: its x column from e_x, its y column from the e_y sums, z from the e_z sums
    bxx = _dot3(ex, a[0], b[0], c[0])
    byx = _dot3(ex, a[1], b[1], c[1])
    bxy = _dot3(wx, a[9], b[9], c[9])
    byy = _dot3(wx, a[10], b[10], c[10])
    lxx = ih * _dot3(dx, a[0], b[0], c[0])
    lyx = ih * _dot3(dx, a[1], b[1], c[1])
    lxy = ih * _dot3(wx, a[6], b[6], c[6])
    lyy = ih * _dot3(wx, a[7], b[7], c[7])
    if D == 2:
        return (ux, uy, 0.0, ox, oy, 0.0, bxx, bxy, 0.0, byx, byy, 0.0, 0.0, 0.0, 0.0,
                lxx, lxy, 0.0, lyx, lyy, 0.0, 0.0, 0.0, 0.0)  # fmt: skip
    uz = _dot3(wx, a[2], b[2], c[2])
    oz = _dot3(wx, a[5], b[5], c[5])
    bzx = _dot3(ex, a[2], b[2], c[2])
    bzy = _dot3(wx, a[11], b[11], c[11])
    bxz = _dot3(wx, a[15], b[15], c[15])
    byz = _dot3(wx, a[16], b[16], c[16])
    bzz = _dot3(wx, a[17], b[17], c[17])
    lzx = ih * _dot3(dx, a[2], b[2], c[2])
    lzy = ih * _dot3(wx, a[8], b[8], c[8])
    lxz = ih * _dot3(wx, a[12], b[12], c[12])
    lyz = ih * _dot3(wx, a[13], b[13], c[13])
    lzz = ih * _dot3(wx, a[14], b[14], c[14])
    return (ux, uy, uz, ox, oy, oz, bxx, bxy, bxz, byx, byy, byz, bzx, bzy, bzz,
            lxx, lxy, lxz, lyx, lyy, lyz, lzx, lzy, lzz)  # fmt: skip


@njit(cache=True, error_model="numpy", inline="always")
def det_update(J, dt, lxx, lxy, lxz, lyx, lyy, lyz, lzx, lzy, lzz):
    """J det(I + Δt L)."""
    a = 1.0 + dt * lxx
    e = 1.0 + dt * lyy
    i = 1.0 + dt * lzz
    b = dt * lxy
    c = dt * lxz
    d = dt * lyx
    f = dt * lyz
    g = dt * lzx
    hh = dt * lzy
    return J * (a * (e * i - f * hh) - b * (d * i - f * g) + c * (d * hh - e * g))


@njit(cache=True, error_model="numpy", inline="always")
def _inside(xi, yi, zi, nx, ny, nz, periodic):
    """True if a point at grid coordinates (ξ, η, ζ) = (x − x₀)/h … has its whole stencil
    inside the grid: 0.5 ≤ ξ < n − 1.5 on every non-periodic axis."""
    if not (yi >= 0.5 and yi < ny - 1.5):
        return False
    if not periodic and not (xi >= 0.5 and xi < nx - 1.5):
        return False
    if D == 3 and not (zi >= 0.5 and zi < nz - 1.5):
        return False
    return True


@njit(cache=True, error_model="numpy", parallel=True, fastmath={"contract"})
def g2p(P, G, prm, dt, nslabs):
    """G2P (APIC, or AFLIP: the FLIP increment blended with α), advection, C = (4/h²) B, L, J
    (J later, from the smoothed L, with ``prm.dilatation``). MUSL (``TRANSFER_FLIP``): the
    velocity blend of AFLIP and the advection only; ``musl_gradient`` gives L and J."""
    ny = G.gv.shape[1]
    nz = _nz(G.gv.shape[2])
    gvf = G.gv.reshape(G.gv.size)
    pr = prm[0]
    ih = 1.0 / pr.h
    k4 = 4.0 * ih * ih
    musl = pr.transfer == TRANSFER_FLIP
    aflip = pr.transfer == TRANSFER_AFLIP or musl
    alpha = pr.flip
    smooth = pr.dilatation != 0
    lx = pr.length_x
    periodic = pr.periodic_x != 0
    # scalars out of the record before the parallel loop (a record's array fields read inside
    # a prange body gave wrong values in the grid check: docs/architecture.md)
    x0 = pr.origin[0]
    y0 = pr.origin[1]
    z0 = pr.origin[2]
    nx = pr.nodes[0]
    ny_ = pr.nodes[1]
    nz_ = pr.nodes[2]
    # the arrays out of the record before the parallel loop: Numba drops writes made through
    # a NamedTuple's fields inside prange (docs/architecture.md, "Numba pitfalls")
    # one array per statement: unpacking a tuple of arrays of mixed dtypes made Numba (0.68)
    # drop the loop's writes to the integer arrays (flags, cursor)
    x = P.x
    v = P.v
    C = P.C
    lg = P.lg
    J = P.J
    flags = P.flags
    cursor = P.cursor
    h = pr.h
    for p in prange(x.shape[1]):
        zp = x[2, p] if D == 3 else 0.0
        r = gather(x[0, p], x[1, p], zp, gvf, h, ih, x0, y0, z0, nx, ny, nz, periodic)
        ux, uy, uz, ox, oy, oz = r[0], r[1], r[2], r[3], r[4], r[5]
        if aflip:
            v[0, p] = alpha * (v[0, p] + ux - ox) + (1.0 - alpha) * ux
            v[1, p] = alpha * (v[1, p] + uy - oy) + (1.0 - alpha) * uy
            if D == 3:
                v[2, p] = alpha * (v[2, p] + uz - oz) + (1.0 - alpha) * uz
        else:
            v[0, p] = ux
            v[1, p] = uy
            if D == 3:
                v[2, p] = uz
        xn = x[0, p] + dt * ux
        yn = x[1, p] + dt * uy
        zn = x[2, p] + dt * uz if D == 3 else 0.0
        if periodic:
            if xn >= lx:
                xn -= lx
            elif xn < 0.0:
                xn += lx
        x[0, p] = xn
        x[1, p] = yn
        if D == 3:
            x[2, p] = zn
        ok = math.isfinite(xn + yn + zn) and _inside((xn - x0) * ih, (yn - y0) * ih,
                                                     (zn - z0) * ih, nx, ny_, nz_, periodic)  # fmt: skip
        flags[p] = ST_OK if ok else ST_LEFT_GRID
        cursor[p] = slab_of(yn, y0, ih, nslabs)
        if musl:  # C stays 0; L and J from the remapped velocities (musl_gradient)
            continue
        bxx, bxy, bxz, byx, byy, byz, bzx, bzy, bzz = r[6:15]
        lxx, lxy, lxz, lyx, lyy, lyz, lzx, lzy, lzz = r[15:24]
        if D == 3:
            _put_mat3(C, p, k4 * bxx, k4 * bxy, k4 * bxz, k4 * byx, k4 * byy, k4 * byz,
                      k4 * bzx, k4 * bzy, k4 * bzz)  # fmt: skip
            _put_mat3(lg, p, lxx, lxy, lxz, lyx, lyy, lyz, lzx, lzy, lzz)
        else:
            C[0, p] = k4 * bxx
            C[1, p] = k4 * bxy
            C[2, p] = k4 * byx
            C[3, p] = k4 * byy
            lg[0, p] = lxx
            lg[1, p] = lxy
            lg[2, p] = lyx
            lg[3, p] = lyy
        if not smooth:  # else J is advanced with the smoothed L (smooth_dilatation)
            J[p] = det_update(J[p], dt, lxx, lxy, lxz, lyx, lyy, lyz, lzx, lzy, lzz)


@njit(cache=True, error_model="numpy", parallel=True)
def momentum_to_velocity(G, prm):
    """MUSL remap: the nodal velocity m v / m of the re-scattered point momenta (``p2g`` with
    ``remap``), with the boundary planes, into the new-velocity lanes."""
    nx, ny, nz = G.nodes.shape[0], G.nodes.shape[1], _nz(G.nodes.shape[2])
    pr = prm[0]
    h = pr.h
    x0 = pr.origin[0]
    y0 = pr.origin[1]
    z0 = pr.origin[2]
    gf = G.nodes.reshape(G.nodes.size)
    gvf = G.gv.reshape(G.gv.size)
    for i in prange(nx):
        for j in range(ny):
            for k in range(nz):
                q = ((i * ny + j) * nz + k) * NF
                o = ((i * ny + j) * nz + k) * NV
                m = gf[q + F_M]
                vx = vy = vz = 0.0
                if m > 0.0:
                    vx = gf[q + F_P] / m
                    vy = gf[q + F_P + 1] / m
                    vz = gf[q + F_P + 2] / m if D == 3 else 0.0
                    vx, vy, vz = apply_planes(prm, x0 + i * h, y0 + j * h, z0 + k * h, vx, vy,
                                              vz)  # fmt: skip
                gvf[o + V_NEW] = vx
                gvf[o + V_NEW + 1] = vy
                if D == 3:
                    gvf[o + V_NEW + 2] = vz


@njit(cache=True, error_model="numpy", parallel=True, fastmath={"contract"})
def musl_gradient(P, G, prm, dt):
    """MUSL: the velocity gradient L = Σ v_i ⊗ ∇w_i of the remapped nodal velocities at the
    positions before G2P (``P.x_old``), and J det(I + Δt L) (unless ``prm.dilatation``, which
    advances J from the smoothed L)."""
    ny = G.gv.shape[1]
    nz = _nz(G.gv.shape[2])
    gvf = G.gv.reshape(G.gv.size)
    pr = prm[0]
    h = pr.h
    ih = 1.0 / h
    smooth = pr.dilatation != 0
    periodic = pr.periodic_x != 0
    x0 = pr.origin[0]
    y0 = pr.origin[1]
    z0 = pr.origin[2]
    nx = pr.nodes[0]
    xo = P.x_old
    lg = P.lg
    J = P.J
    for p in prange(xo.shape[1]):
        zp = xo[2, p] if D == 3 else 0.0
        r = gather(xo[0, p], xo[1, p], zp, gvf, h, ih, x0, y0, z0, nx, ny, nz, periodic)
        lxx, lxy, lxz, lyx, lyy, lyz, lzx, lzy, lzz = r[15:24]
        if D == 3:
            _put_mat3(lg, p, lxx, lxy, lxz, lyx, lyy, lyz, lzx, lzy, lzz)
        else:
            lg[0, p] = lxx
            lg[1, p] = lxy
            lg[2, p] = lyx
            lg[3, p] = lyy
        if not smooth:
            J[p] = det_update(J[p], dt, lxx, lxy, lxz, lyx, lyy, lyz, lzx, lzy, lzz)


# ---------------------------------------------------------------------------------------------
# 4b. volumetric smoothing: the double mapping of the volumetric rate tr L (docs/model.md,
#     "Volumetric smoothing"; González Acosta et al. 2020 map the stress the same way)


@njit(cache=True, error_model="numpy", inline="always")
def _trace(lg, p):
    """tr L of point p (the in-plane trace in 2-D plane strain)."""
    if D == 3:
        return lg[0, p] + lg[4, p] + lg[8, p]
    return lg[0, p] + lg[3, p]


@njit(cache=True, error_model="numpy")
def _dilatation_p2g(P, fw, prm):
    """P2G of m and m tr L into ``fw[W_M]``, ``fw[W_MG]`` (serial: the nodes receive their sums
    in point order, so that the result does not depend on the thread count)."""
    pr = prm[0]
    ih = 1.0 / pr.h
    nx = pr.nodes[0]
    periodic = pr.periodic_x != 0
    x0 = pr.origin[0]
    y0 = pr.origin[1]
    z0 = pr.origin[2]
    x = P.x
    mass = P.mass
    lg = P.lg
    for p in range(x.shape[1]):
        bx, wx0, wx1, wx2, _, _, _, _ = bspline2_frac((x[0, p] - x0) * ih)
        by, wy0, wy1, wy2, _, _, _, _ = bspline2_frac((x[1, p] - y0) * ih)
        zp = x[2, p] if D == 3 else 0.0
        bz, wz0, wz1, wz2, _, _, _, _ = _z_axis(zp, z0, ih)
        wx = (wx0, wx1, wx2)
        wy = (wy0, wy1, wy2)
        wz = (wz0, wz1, wz2)
        m = mass[p]
        mt = m * _trace(lg, p)
        for a in range(3):
            i = _wrap(bx + a, nx) if periodic else bx + a
            for b in range(3):
                j = by + b
                wab = wx[a] * wy[b]
                for c in range(SZ):
                    k = bz + c
                    w = wab * wz[c]
                    fw[W_M, i, j, k] += w * m
                    fw[W_MG, i, j, k] += w * mt


@njit(cache=True, error_model="numpy", parallel=True)
def _dilatation_g2p(P, fw, prm, dt):
    """Each point's tr L replaced by the interpolation of the nodal averages
    Σ_p w m tr L / Σ_p w m (the deviatoric part of L untouched: the isotropic correction
    (tr L̄ − tr L)/D on the diagonal), then J ← J det(I + Δt L̄)."""
    pr = prm[0]
    ih = 1.0 / pr.h
    nx = pr.nodes[0]
    periodic = pr.periodic_x != 0
    x0 = pr.origin[0]
    y0 = pr.origin[1]
    z0 = pr.origin[2]
    x = P.x
    lg = P.lg
    J = P.J
    for p in prange(x.shape[1]):
        bx, wx0, wx1, wx2, _, _, _, _ = bspline2_frac((x[0, p] - x0) * ih)
        by, wy0, wy1, wy2, _, _, _, _ = bspline2_frac((x[1, p] - y0) * ih)
        zp = x[2, p] if D == 3 else 0.0
        bz, wz0, wz1, wz2, _, _, _, _ = _z_axis(zp, z0, ih)
        wx = (wx0, wx1, wx2)
        wy = (wy0, wy1, wy2)
        wz = (wz0, wz1, wz2)
        num = 0.0
        wsum = 0.0
        for a in range(3):
            i = _wrap(bx + a, nx) if periodic else bx + a
            for b in range(3):
                j = by + b
                wab = wx[a] * wy[b]
                for c in range(SZ):
                    k = bz + c
                    m = fw[W_M, i, j, k]
                    if m > 0.0:
                        w = wab * wz[c]
                        num += w * fw[W_MG, i, j, k] / m
                        wsum += w
        if wsum > 0.0:
            d = (num / wsum - _trace(lg, p)) / D
            lg[0, p] += d
            if D == 3:
                lg[4, p] += d
                lg[8, p] += d
            else:
                lg[3, p] += d
        lxx, lxy, lxz, lyx, lyy, lyz, lzx, lzy, lzz = _mat(lg, p)
        J[p] = det_update(J[p], dt, lxx, lxy, lxz, lyx, lyy, lyz, lzx, lzy, lzz)


@njit(cache=True, error_model="numpy")
def smooth_dilatation(P, G, prm, dt):
    """The volumetric smoothing of ``prm.dilatation``: tr L mapped to the grid and back, so that
    the points of a cell share one volumetric rate (the null mode of 2 points per cell and
    axis, alternate rows compressed and dilated, then has no source), then J from it."""
    fw = G.fw
    fw[W_M] = 0.0
    fw[W_MG] = 0.0
    _dilatation_p2g(P, fw, prm)
    _dilatation_g2p(P, fw, prm, dt)


# ---------------------------------------------------------------------------------------------
# 5. material law: Fei et al. 2016 in full tensor form


#: 1/3
THIRD = 1.0 / 3.0


@njit(cache=True, error_model="numpy", inline="always")
def _shear_sq(xy, xz, yz):
    """xy² + xz² + yz² of a symmetric tensor's shear components (xy² in 2-D).

    The out-of-plane terms of the laws are written under ``if D == 3`` (here and in
    :func:`_kinematics`, :func:`fei_tensor`, :func:`ngf_tensor`): IEEE arithmetic cannot drop
    0 · x or x + 0 (x could be NaN, −0), so a zero component left in an expression costs its
    operations at run time; in 2-D they were a fifth of the material pass."""
    if D == 3:
        return xy * xy + xz * xz + yz * yz
    return xy * xy


@njit(cache=True, error_model="numpy", inline="always")
def _kinematics(L, e, dt):
    """The rate of deformation of L and the objective predictor of ε: the deviatoric rate d′
    (xx, yy, zz), the shear rates d (xy, xz, yz), tr d, γ̇ = √(2 d′:d′), and the Jaumann
    predictor ε + Δt (d + w ε − ε w) (xx, yy, zz, xy, xz, yz). In 2-D (plane strain: L and ε
    have no xz, yz and L no zz) the z terms are left out (:func:`_shear_sq`)."""
    lxx, lxy, lxz, lyx, lyy, lyz, lzx, lzy, lzz = L
    exx, eyy, ezz, exy, exz, eyz = e
    dxy = 0.5 * (lxy + lyx)
    wxy = 0.5 * (lxy - lyx)
    dxz = dyz = wxz = wyz = 0.0
    trd = lxx + lyy
    if D == 3:
        dxz = 0.5 * (lxz + lzx)
        dyz = 0.5 * (lyz + lzy)
        wxz = 0.5 * (lxz - lzx)
        wyz = 0.5 * (lyz - lzy)
        trd += lzz
    t3 = trd * THIRD
    dpxx = lxx - t3
    dpyy = lyy - t3
    dpzz = lzz - t3 if D == 3 else -t3
    gdot = fsqrt(2.0 * (dpxx * dpxx + dpyy * dpyy + dpzz * dpzz
                        + 2.0 * _shear_sq(dxy, dxz, dyz)))  # fmt: skip
    # Jaumann predictor: w ε − ε w = M + Mᵀ with M = w ε
    mxx = wxy * exy
    myy = -wxy * exy
    qxy = wxy * eyy - wxy * exx
    if D == 3:
        mxx += wxz * exz
        myy += wyz * eyz
        mzz = -wxz * exz - wyz * eyz
        qxy += wxz * eyz + wyz * exz
        qxz = wxy * eyz + wxz * ezz - wxz * exx - wyz * exy
        qyz = -wxy * exz + wyz * ezz - wxz * exy - wyz * eyy
        ezz = ezz + dt * (lzz + 2.0 * mzz)
        exz = exz + dt * (dxz + qxz)
        eyz = eyz + dt * (dyz + qyz)
    exx = exx + dt * (lxx + 2.0 * mxx)
    eyy = eyy + dt * (lyy + 2.0 * myy)
    exy = exy + dt * (dxy + qxy)
    return dpxx, dpyy, dpzz, dxy, dxz, dyz, trd, gdot, exx, eyy, ezz, exy, exz, eyz


@njit(cache=True, error_model="numpy", inline="always")
def _or_gas(gas, third, r):
    """The gas state where ``gas`` (I₁ ≤ 0: no contacts, no stress, the volumetric strain
    keeps tracking the density; γ̇ kept), else the law's result ``r``: one select per
    component, no branch, so that the loop over points vectorises."""
    v = -third
    z = 0.0
    return (v if gas else r[0], v if gas else r[1], v if gas else r[2], z if gas else r[3],
            z if gas else r[4], z if gas else r[5], z if gas else r[6], z if gas else r[7],
            z if gas else r[8], z if gas else r[9], z if gas else r[10], z if gas else r[11],
            z if gas else r[12], r[13], z if gas else r[14], z if gas else r[15],
            z if gas else r[16], z if gas else r[17])  # fmt: skip


@njit(cache=True, error_model="numpy", inline="always")
def fei_tensor(mat, L, e, J, phi, dt, linear):
    """Stress update of one point, Fei et al. 2016 (docs/model.md §1) in full tensor form.

    ``L`` the velocity gradient (row-major 3×3), ``e`` the elastic strain (xx, yy, zz, xy, xz,
    yz), J the volume ratio (I₁ = −ln J), φ_s. Steps: objective (Jaumann) predictor
    ε + Δt (d + w ε − ε w); the yield cap √I₂ ≤ r_c I₁/q_φ on the deviator; the Jiang–Liu stress
    σ^e = −p_e 1 + C √I₁ ε⁰; the dissipative σ^d = 2 η d′ with η = a d̄^b ρ_s^{b/2} p_e^{1−b/2}
    γ̇^{b−1} (d̄ = φ_s d_s + (1 − φ_s) d_l); a bulk viscosity ζ ρ c h tr d; the gas state (no
    stress) for I₁ ≤ 0. Returns (ε⁶, σ⁶, p_e, γ̇, I, S, c, ν).

    ``linear``: b = 1 (η = a d̄ √(ρ_s p_e), no powers); a compile-time constant in the material
    pass, as is the model, so that the loop over points vectorises. The gas state is selected at
    the end rather than returned early, for the same reason."""
    dpxx, dpyy, dpzz, dxy, dxz, dyz, trd, gdot, exx, eyy, ezz, exy, exz, eyz = _kinematics(
        L, e, dt)  # fmt: skip
    t3 = (exx + eyy + ezz) * THIRD
    e0xx = exx - t3
    e0yy = eyy - t3
    e0zz = ezz - t3
    I2 = 0.5 * (e0xx * e0xx + e0yy * e0yy + e0zz * e0zz + 2.0 * _shear_sq(exy, exz, eyz))
    I1 = -flog(J)
    cap = mat.capr * I1
    over = I2 > cap * cap
    s = cap / fsqrt(I2) if over else 1.0
    e0xx *= s
    e0yy *= s
    e0zz *= s
    e0xy = exy * s
    e0xz = exz * s if D == 3 else 0.0
    e0yz = eyz * s if D == 3 else 0.0
    I2 = cap * cap if over else I2
    third = I1 * THIRD
    gas = I1 <= 0.0  # no contacts, no stress: selected at the end
    A = mat.a
    Cj = mat.c
    rho_s = mat.rho_s
    rho = mat.f * rho_s / J
    sq = fsqrt(I1 if I1 > 0.0 else 1.0)
    pe = 2.5 * A * I1 * sq + 0.5 * Cj * I2 / sq
    G2 = Cj * sq
    dbar = phi * mat.ds + (1.0 - phi) * mat.dl
    spe = fsqrt(rho_s * pe)
    a = mat.mu_a * mat.sdf
    b = mat.mu_b
    if linear:
        eta = a * dbar * spe
    else:
        g = max(gdot, mat.gfloor)
        eta = a * dbar**b * rho_s ** (0.5 * b) * pe ** (1.0 - 0.5 * b) * g ** (b - 1.0)
    inertial = gdot * dbar * rho_s / spe if pe > 0.0 else 0.0
    c = fsqrt(mat.cw * sq * J * mat.irho0)
    zeta = mat.zeta * rho * c * mat.h
    vol = zeta * trd - pe
    sxx = G2 * e0xx + 2.0 * eta * dpxx + vol
    syy = G2 * e0yy + 2.0 * eta * dpyy + vol
    szz = G2 * e0zz + 2.0 * eta * dpzz + vol
    sxy = G2 * e0xy + 2.0 * eta * dxy
    sxz = G2 * e0xz + 2.0 * eta * dxz if D == 3 else 0.0
    syz = G2 * e0yz + 2.0 * eta * dyz if D == 3 else 0.0
    driver = int(mat.driver)
    if driver == DRIVER_A:
        S = eta * gdot
    elif driver == DRIVER_B:
        S = mat.kappa_t * rho * (gdot * dbar) ** 2
    elif driver == DRIVER_P:
        S = pe
    else:
        S = -2.0 * eta * dpyy
    S *= mat.kappa
    nu = (eta + zeta) * J * mat.irho0
    r = (e0xx - third, e0yy - third, e0zz - third, e0xy, e0xz, e0yz,
         sxx, syy, szz, sxy, sxz, syz, pe, gdot, inertial, S, c, nu)  # fmt: skip
    return _or_gas(gas, third, r)


@njit(cache=True, error_model="numpy", inline="always")
def elastic_tensor(mat, L, e, J, phi, dt):
    """Linear (Hooke) elasticity with the Jaumann predictor: σ = λ tr ε 1 + 2 μ ε (tests); the
    shear-rate diagnostic γ̇ as the other laws report it."""
    _, _, _, _, _, _, _, gdot, exx, eyy, ezz, exy, exz, eyz = _kinematics(L, e, dt)
    lam = mat.lame_lambda
    mu = mat.mu
    tr = exx + eyy + ezz
    rho = mat.f * mat.rho_s / J
    c = math.sqrt((lam + 2.0 * mu) / rho)
    return (exx, eyy, ezz, exy, exz, eyz, lam * tr + 2.0 * mu * exx, lam * tr + 2.0 * mu * eyy,
            lam * tr + 2.0 * mu * ezz, 2.0 * mu * exy, 2.0 * mu * exz if D == 3 else 0.0,
            2.0 * mu * eyz if D == 3 else 0.0,
            -tr * (lam + 2.0 * mu / 3.0), gdot, 0.0, 0.0, c, 0.0)  # fmt: skip


@njit(cache=True, error_model="numpy", inline="always")
def ngf_tensor(mat, L, e, J, phi, g, dt):
    """Stress update of one point with the fluidity flow rule of the nonlocal rheology
    (docs/model.md, "Nonlocal rheology"), in full tensor form: the objective predictor, then the
    implicit return ε⁰ ← f ε⁰_tr of γ̇ᵖ = g μ with f (p(f) + G Δt g) = p(f) (G = C√I₁/2, p the
    Jiang–Liu pressure of the returned state: ``materials.ngf.return_factor``), the convexity
    guard √I₂ ≤ r_c I₁/q_φ, the Jiang–Liu stress and a bulk viscosity; no σ^d (the rate
    dependence is the fluidity's). ``g`` the point's fluidity (1/s). The contract of
    :func:`fei_tensor`."""
    dpxx, dpyy, dpzz, dxy, dxz, dyz, trd, gdot, exx, eyy, ezz, exy, exz, eyz = _kinematics(
        L, e, dt)  # fmt: skip
    t3 = (exx + eyy + ezz) * THIRD
    e0xx = exx - t3
    e0yy = eyy - t3
    e0zz = ezz - t3
    I2 = 0.5 * (e0xx * e0xx + e0yy * e0yy + e0zz * e0zz + 2.0 * _shear_sq(exy, exz, eyz))
    I1 = -flog(J)
    third = I1 * THIRD
    gas = I1 <= 0.0  # selected at the end (fei_tensor)
    A = mat.a
    Cj = mat.c
    rho_s = mat.rho_s
    rho = mat.f * rho_s / J
    sq = fsqrt(I1 if I1 > 0.0 else 1.0)
    isq = 1.0 / sq
    a0 = 2.5 * A * I1 * sq
    k = 0.5 * Cj * sq * dt * g
    # a trial state so far out that the return's cubic could have several roots is first
    # pulled back onto a2 = 2 (a0 + k) (materials.ngf.return_factor)
    lim = 4.0 * (a0 + k) * sq / Cj
    over = I2 > lim
    s = fsqrt(lim / I2) if over else 1.0
    I2 = lim if over else I2
    f = s * return_factor(a0, 0.5 * Cj * I2 * isq, k)
    I2 *= (f / s) * (f / s)
    cap = mat.capr * I1
    over = I2 > cap * cap
    f *= cap / fsqrt(I2) if over else 1.0
    I2 = cap * cap if over else I2
    e0xx *= f
    e0yy *= f
    e0zz *= f
    e0xy = exy * f
    e0xz = exz * f if D == 3 else 0.0
    e0yz = eyz * f if D == 3 else 0.0
    pe = 2.5 * A * I1 * sq + 0.5 * Cj * I2 * isq
    G2 = Cj * sq
    dbar = phi * mat.ds + (1.0 - phi) * mat.dl
    spe = fsqrt(rho_s * pe)
    inertial = gdot * dbar * rho_s / spe if pe > 0.0 else 0.0
    c = fsqrt(mat.cw * sq * J * mat.irho0)
    zeta = mat.zeta * rho * c * mat.h
    vol = zeta * trd - pe
    sxx = G2 * e0xx + vol
    syy = G2 * e0yy + vol
    szz = G2 * e0zz + vol
    sxy = G2 * e0xy
    sxz = G2 * e0xz if D == 3 else 0.0
    syz = G2 * e0yz if D == 3 else 0.0
    driver = int(mat.driver)
    if driver == DRIVER_A:
        S = mat.ngf_b * inertial * pe  # the rate-dependent part b I p of the local law
    elif driver == DRIVER_B:
        S = mat.kappa_t * rho * (gdot * dbar) ** 2
    elif driver == DRIVER_C:
        S = 0.0
    elif driver == DRIVER_P:
        S = pe
    else:
        S = mat.kappa_g * rho * (g * dbar) ** 2
    S *= mat.kappa
    nu = zeta * J * mat.irho0
    r = (e0xx - third, e0yy - third, e0zz - third, e0xy, e0xz, e0yz,
         sxx, syy, szz, sxy, sxz, syz, pe, gdot, inertial, S, c, nu)  # fmt: skip
    return _or_gas(gas, third, r)


#: the constitutive laws, each a compile-time constant of the material pass (``law``)
LAW_ELASTIC = VAR_ELASTIC
LAW_FEI = VAR_FEI_LINEAR  # Fei et al. 2016 with b = 1
LAW_FEI_POWER = VAR_FEI_POWER  # the same with b ≠ 1
LAW_NGF = VAR_NGF  # Jiang–Liu elasticity with the fluidity flow rule (nonlocal rheology)
#: points per block of the material pass (the update loop vectorises within a block)
BLOCK = 512


@njit(cache=True, error_model="numpy", inline="always")
def law_of(mat):
    """The law of the record (``LAW_*``), chosen at set-up by ``mat.kind`` and b."""
    m = mat[0]
    if m.kind == KIND_FEI2016_NGF:
        return LAW_NGF
    if m.kind == KIND_FEI2016:
        return LAW_FEI if m.mu_b == 1.0 else LAW_FEI_POWER
    return LAW_ELASTIC


@njit(cache=True, error_model="numpy", inline="always")
def law(which, mat, L, e, J, phi, g, dt):
    """The constitutive law ``which`` (``LAW_*``, a constant where the material pass calls it):
    the extension point for a new model (docs/architecture.md). A function of (record, L, ε,
    J, φ_s, g, Δt) with the return contract of :func:`fei_tensor` (``g`` the point's fluidity,
    read by the nonlocal law only)."""
    m = mat[0]
    if which == LAW_FEI:
        return fei_tensor(m, L, e, J, phi, dt, True)
    if which == LAW_NGF:
        return ngf_tensor(m, L, e, J, phi, g, dt)
    if which == LAW_FEI_POWER:
        return fei_tensor(m, L, e, J, phi, dt, False)
    return elastic_tensor(m, L, e, J, phi, dt)


@njit(cache=True, error_model="numpy", inline="always")
def material(mat, L, e, J, phi, g, dt):
    """The law of the record at one point (dispatched at run time: tests and diagnostics)."""
    return law(law_of(mat), mat, L, e, J, phi, g, dt)


@njit(cache=True, error_model="numpy", inline="always")
def _stress_block(which, lo, m, buf, P, mat, dt):
    """The material update of points lo … lo + m − 1 with the law ``which`` (a constant): state,
    stress and p_e stored, the diagnostics and the step check (1.0: failed) into ``buf``.
    Unsigned indices (no negative-index wrap), no call and no reduction: the loop vectorises."""
    v = P.v
    J = P.J
    eps = P.eps
    sig = P.sig
    phi = P.phi
    diag = P.diag
    s_int = P.s_int
    g_int = P.g_int
    lg = P.lg
    flags = P.flags
    gf = P.gf
    base = np.uint64(lo)
    for u in range(np.uint64(m)):
        p = base + u
        Jp = J[p]
        r = law(which, mat, _mat(lg, p), _sym(eps, p), Jp, phi[p], gf[p], dt)
        _put_sym(eps, p, r[0], r[1], r[2], r[3], r[4], r[5])
        _put_sym(sig, p, r[6], r[7], r[8], r[9], r[10], r[11])
        diag[0, p] = r[12]
        s_int[p] += r[15] * dt
        g_int[p] += r[13] * dt
        vx, vy, vz = _vec(v, p)
        v2 = vx * vx + vy * vy
        ssum = r[6] + r[7] + r[8] + r[9]
        if D == 3:  # (out-of-plane terms: _shear_sq)
            v2 += vz * vz
            ssum += r[10] + r[11]
        speed = r[16] + fsqrt(v2)
        ok = flags[p] == ST_OK and math.isfinite(speed) and math.isfinite(ssum) and Jp > 0.0
        buf[B_GDOT, u] = r[13]
        buf[B_I, u] = r[14]
        buf[B_S, u] = r[15]
        buf[B_SPEED, u] = speed
        buf[B_NU, u] = r[17]
        buf[B_BAD, u] = 0.0 if ok else 1.0


# ---------------------------------------------------------------------------------------------
# 5b. nonlocal fluidity: diffusion on the MPM grid, local relaxation at the points
#     (docs/model.md, "Nonlocal rheology"; the scheme, constants and boundary rules of
#     segmpm.mpm.fluidity, written for D dimensions)

#: fields of the fluidity work array ``G.fw`` (NW, n_x, n_y, n_z): the P2G sums of m, m g, m φ_s,
#: the nodal g and its value before the diffusion, the node diffusivity A² d̄²/t₀, the capacity
#: (filled part of the control volume), the Laplacian of a sub-step, the node kind
W_M, W_MG, W_MPHI, W_G, W_G0, W_DIFF, W_CAP, W_LAP, W_KIND = range(9)
NW = 9
#: node kinds (``W_KIND``): no material, fluidity carrying, Dirichlet g = 0 (rough walls)
K_EMPTY, K_ACTIVE, K_DIRICHLET = 0.0, 1.0, 2.0


@njit(cache=True, error_model="numpy")
def _fluidity_p2g(P, fw, prm):
    """P2G of m, m g and m φ_s (serial: the nodes receive their sums in point order)."""
    pr = prm[0]
    ih = 1.0 / pr.h
    nx = pr.nodes[0]
    periodic = pr.periodic_x != 0
    x0 = pr.origin[0]
    y0 = pr.origin[1]
    z0 = pr.origin[2]
    x = P.x
    mass = P.mass
    gf = P.gf
    phi = P.phi
    for p in range(x.shape[1]):
        bx, wx0, wx1, wx2, _, _, _, _ = bspline2_frac((x[0, p] - x0) * ih)
        by, wy0, wy1, wy2, _, _, _, _ = bspline2_frac((x[1, p] - y0) * ih)
        if D == 3:
            zp = x[2, p]
        else:
            zp = 0.0
        bz, wz0, wz1, wz2, _, _, _, _ = _z_axis(zp, z0, ih)
        wx = (wx0, wx1, wx2)
        wy = (wy0, wy1, wy2)
        wz = (wz0, wz1, wz2)
        m = mass[p]
        mg = m * gf[p]
        mf = m * phi[p]
        for a in range(3):
            i = _wrap(bx + a, nx) if periodic else bx + a
            for b in range(3):
                j = by + b
                wab = wx[a] * wy[b]
                for c in range(SZ):
                    k = bz + c
                    w = wab * wz[c]
                    fw[W_M, i, j, k] += w * m
                    fw[W_MG, i, j, k] += w * mg
                    fw[W_MPHI, i, j, k] += w * mf


@njit(cache=True, error_model="numpy")
def fluidity_planes(prm):
    """The zero-flux planes of the fluidity that lie on a node plane (slip, Coulomb and symmetry
    planes: the base, x = xlo, xhi if x is not periodic, z = zlo, zhi in 3-D), rows (axis, node
    index of the plane, side −1 below / +1 above). The fluidity is extended evenly across them
    (image nodes, :func:`fold_fluidity`), so that a node on the plane has the full control volume
    and its faces along the plane the full area."""
    pr = prm[0]
    out = np.full((5, 3), -1, dtype=np.int64)
    r = 0
    kinds = (pr.base_kind, pr.xlo_kind, pr.xhi_kind, pr.zlo_kind, pr.zhi_kind)
    where = (pr.base_y, pr.xlo, pr.xhi, pr.zlo, pr.zhi)
    axes = (1, 0, 0, 2, 2)
    sides = (-1, -1, 1, -1, 1)
    for q in range(5):
        a = axes[q]
        if kinds[q] == BC_OPEN or kinds[q] == BC_NOSLIP:
            continue
        if (a == 0 and pr.periodic_x != 0) or (a == 2 and D != 3):
            continue
        k = _plane_node(where[q], pr.origin[a], pr.h, pr.nodes[a])
        if k < 0:
            continue
        out[r, 0] = a
        out[r, 1] = k
        out[r, 2] = sides[q]
        r += 1
    return out[:r]


@njit(cache=True, error_model="numpy", inline="always")
def _image_of(i, j, k, axis, kw, side, nx, ny, nz):
    """(i, j, k) of the mirror of a node behind the plane, or (−1, −1, −1)."""
    mi = _mirror_index(i, j, k, axis, kw, side)
    if mi < 0:
        return -1, -1, -1
    im, jm, km = i, j, k
    if axis == 0:
        im = mi
    elif axis == 1:
        jm = mi
    else:
        km = mi
    if im < 0 or im >= nx or jm < 0 or jm >= ny or km < 0 or km >= nz:
        return -1, -1, -1
    return im, jm, km


@njit(cache=True, error_model="numpy")
def fold_fluidity(fw, planes):
    """Even extension of the P2G sums across the zero-flux planes: a node behind a plane adds
    its sums to its mirror node; a node on the plane doubles its own (its mirror is itself) —
    the sums of the material and its mirror image. Then, once every plane is folded, each node
    behind a plane takes its mirror's sums (so that two planes a few cells apart, or a corner,
    see the folded values)."""
    nx, ny, nz = fw.shape[1], fw.shape[2], _nz(fw.shape[3])
    for r in range(planes.shape[0]):
        axis, kw, side = planes[r, 0], planes[r, 1], planes[r, 2]
        for i in range(nx):
            for j in range(ny):
                for k in range(nz):
                    c = i if axis == 0 else (j if axis == 1 else k)
                    if c == kw:
                        for f in (W_M, W_MG, W_MPHI):
                            fw[f, i, j, k] *= 2.0
                        continue
                    im, jm, km = _image_of(i, j, k, axis, kw, side, nx, ny, nz)
                    if im < 0:
                        continue
                    for f in (W_M, W_MG, W_MPHI):
                        fw[f, im, jm, km] += fw[f, i, j, k]
                        fw[f, i, j, k] = 0.0
    for r in range(planes.shape[0]):
        axis, kw, side = planes[r, 0], planes[r, 1], planes[r, 2]
        for i in range(nx):
            for j in range(ny):
                for k in range(nz):
                    im, jm, km = _image_of(i, j, k, axis, kw, side, nx, ny, nz)
                    if im >= 0:
                        for f in (W_M, W_MG, W_MPHI):
                            fw[f, i, j, k] = fw[f, im, jm, km]


@njit(cache=True, error_model="numpy")
def mirror_fluidity(fw, planes):
    """The nodal g behind the zero-flux planes: that of the mirror nodes (after a sub-step)."""
    nx, ny, nz = fw.shape[1], fw.shape[2], _nz(fw.shape[3])
    for r in range(planes.shape[0]):
        axis, kw, side = planes[r, 0], planes[r, 1], planes[r, 2]
        for i in range(nx):
            for j in range(ny):
                for k in range(nz):
                    im, jm, km = _image_of(i, j, k, axis, kw, side, nx, ny, nz)
                    if im >= 0 and fw[W_KIND, i, j, k] == K_ACTIVE:
                        fw[W_G, i, j, k] = fw[W_G, im, jm, km]


@njit(cache=True, error_model="numpy", inline="always")
def _rough(kind, at, where, tol, side):
    """True if a node at coordinate ``at`` lies at or beyond a no-slip plane at ``where``."""
    if kind != BC_NOSLIP:
        return False
    return at <= where + tol if side < 0 else at >= where - tol


@njit(cache=True, error_model="numpy", parallel=True)
def _fluidity_nodes(fw, prm, mat, serial):
    """Nodal g, diffusivity, capacity and kind from the P2G sums; returns max D/c (the explicit
    stability limit). The free surface is a zero-flux cut cell (capacity c = clamp(1.5 m/m_full −
    0.25, 0, 1)); nodes at and beyond a no-slip plane are Dirichlet nodes (g = 0); the
    frictional, slip and symmetry planes on node planes are zero-flux by the even extension
    (``fold_fluidity``). The x-planes in parallel, or in order on one thread (a parallel region
    costs microseconds, several per cent of the default run's step); the same result."""
    pr = prm[0]
    m0 = mat[0]
    nx = fw.shape[1]
    h = pr.h
    # the scalars out of the records before the parallel loop (docs/architecture.md, "Numba
    # pitfalls")
    wall = (pr.base_kind, pr.xlo_kind, pr.xhi_kind, pr.zlo_kind, pr.zhi_kind)
    at = (pr.base_y, pr.xlo, pr.xhi, pr.zlo, pr.zhi)
    closed = pr.periodic_x == 0
    m_full = m0.f * m0.rho_s * h**D
    coef = m0.ngf_a**2 / m0.t0
    ds, dl = m0.ds, m0.dl
    x0, y0, z0 = pr.origin[0], pr.origin[1], pr.origin[2]
    dmax = 0.0
    if serial:
        for i in range(nx):
            dmax = max(dmax, _fluidity_nodes_plane(fw, i, h, x0, y0, z0, closed, wall, at,
                                                   m_full, coef, ds, dl))  # fmt: skip
    else:
        for i in prange(nx):
            dmax = max(dmax, _fluidity_nodes_plane(fw, i, h, x0, y0, z0, closed, wall, at,
                                                   m_full, coef, ds, dl))  # fmt: skip
    return dmax


@njit(cache=True, error_model="numpy", inline="always")
def _fluidity_nodes_plane(fw, i, h, x0, y0, z0, closed, wall, at, m_full, coef, ds, dl):
    """The nodes of the x-plane ``i`` (``_fluidity_nodes``; ``wall``/``at`` the kinds and
    positions of the base, x- and z-planes); returns their max D/c."""
    ny, nz = fw.shape[2], _nz(fw.shape[3])
    tol = 1e-9 * h
    dmax = 0.0
    xn = x0 + i * h
    for j in range(ny):
        yn = y0 + j * h
        for k in range(nz):
            zn = z0 + k * h
            m = fw[W_M, i, j, k]
            cap = min(1.0, max(0.0, FILL_SLOPE * m / m_full - FILL_OFFSET))
            kind = K_ACTIVE if cap > 0.0 else K_EMPTY
            rough = _rough(wall[0], yn, at[0], tol, -1)
            if closed:
                rough = (rough or _rough(wall[1], xn, at[1], tol, -1)
                         or _rough(wall[2], xn, at[2], tol, 1))  # fmt: skip
            if D == 3:
                rough = (rough or _rough(wall[3], zn, at[3], tol, -1)
                         or _rough(wall[4], zn, at[4], tol, 1))  # fmt: skip
            if rough:
                kind = K_DIRICHLET
            g = 0.0
            dn = 0.0
            if kind == K_ACTIVE:
                g = fw[W_MG, i, j, k] / m
                ph = min(1.0, max(0.0, fw[W_MPHI, i, j, k] / m))
                d = ph * ds + (1.0 - ph) * dl
                dn = coef * d * d
                dmax = max(dmax, dn / max(cap, CAPACITY_MIN))
            fw[W_DIFF, i, j, k] = dn
            fw[W_CAP, i, j, k] = max(cap, CAPACITY_MIN) if kind == K_ACTIVE else 0.0
            fw[W_KIND, i, j, k] = kind
            fw[W_G, i, j, k] = g
            fw[W_G0, i, j, k] = g
    return dmax


@njit(cache=True, error_model="numpy", inline="always")
def _flux(kind, diff, g, a, b, c, di, gi):
    """D_f (g_n − g_i) from a node of diffusivity di and fluidity gi to its neighbour (a, b, c):
    the face diffusivity is the mean of the two nodes' (the active node's towards a Dirichlet
    node); none into empty nodes."""
    kn = kind[a, b, c]
    if kn == K_ACTIVE:
        return 0.5 * (di + diff[a, b, c]) * (g[a, b, c] - gi)
    if kn == K_DIRICHLET:
        return -di * gi
    return 0.0


@njit(cache=True, error_model="numpy", inline="always")
def _laplacian_plane(kind, diff, g, lap, i, nx, ny, nz, periodic, ih2):
    """The flux sum Σ_faces D_f (g_j − g_i)/h² of every active node of the x-plane i into
    ``lap`` (``kind``, ``diff``, ``g``: those fields of ``fw``; a grid one node wide and periodic
    in x, the column's, has no x-faces but to the node itself, whose flux is zero: skipped)."""
    ilo = _wrap(i - 1, nx) if periodic else i - 1
    ihi = _wrap(i + 1, nx) if periodic else i + 1
    xfaces = not (periodic and nx == 1)
    for j in range(ny):
        for k in range(nz):
            lap[i, j, k] = 0.0
            if kind[i, j, k] != K_ACTIVE:
                continue
            di = diff[i, j, k]
            gi = g[i, j, k]
            acc = 0.0
            if xfaces:
                if ilo >= 0:
                    acc += _flux(kind, diff, g, ilo, j, k, di, gi)
                if ihi < nx:
                    acc += _flux(kind, diff, g, ihi, j, k, di, gi)
            if j > 0:
                acc += _flux(kind, diff, g, i, j - 1, k, di, gi)
            if j < ny - 1:
                acc += _flux(kind, diff, g, i, j + 1, k, di, gi)
            if D == 3:
                if k > 0:
                    acc += _flux(kind, diff, g, i, j, k - 1, di, gi)
                if k < nz - 1:
                    acc += _flux(kind, diff, g, i, j, k + 1, di, gi)
            lap[i, j, k] = acc * ih2


@njit(cache=True, error_model="numpy", inline="always")
def _advance_plane(kind, g, lap, cap, i, ny, nz, ds):
    """g ← g + Δs (flux sum)/c on the active nodes of the x-plane i."""
    for j in range(ny):
        for k in range(nz):
            if kind[i, j, k] == K_ACTIVE:
                g[i, j, k] += ds * lap[i, j, k] / cap[i, j, k]


@njit(cache=True, error_model="numpy", parallel=True)
def diffuse(fw, prm, dt, dmax, planes, serial=False):
    """Explicit finite-volume diffusion of the nodal g over ``dt`` in sub-steps below the
    stability limit h²/(2 D max D/c): c_i ∂g_i/∂t = Σ_faces D_f (g_j − g_i)/h² over the 2 D
    neighbours (periodic in x if the grid is). Returns the number of sub-steps. The x-planes
    in parallel; a grid one node wide (the column model), or any grid on one thread, serially,
    without the cost of two parallel regions per sub-step (4× the former plane-strain column's fluidity
    step with them)."""
    if not (dmax > 0.0) or not (dt > 0.0):
        return 0
    pr = prm[0]
    nx, ny, nz = fw.shape[1], fw.shape[2], _nz(fw.shape[3])
    ih2 = 1.0 / (pr.h * pr.h)
    periodic = pr.periodic_x != 0
    nsub = max(1, int(math.ceil(dt * 2.0 * D * dmax * ih2 / SAFETY)))
    ds = dt / nsub
    # the fields once, not per plane and sub-step (a view costs its reference counting)
    kind = fw[W_KIND]
    diff = fw[W_DIFF]
    g = fw[W_G]
    lap = fw[W_LAP]
    cap = fw[W_CAP]
    images = planes.shape[0] > 0
    for _ in range(nsub):
        if nx == 1:
            _laplacian_plane(kind, diff, g, lap, 0, nx, ny, nz, periodic, ih2)
            _advance_plane(kind, g, lap, cap, 0, ny, nz, ds)
        elif serial:  # the same planes in order: the same result without the regions' cost
            for i in range(nx):
                _laplacian_plane(kind, diff, g, lap, i, nx, ny, nz, periodic, ih2)
            for i in range(nx):
                _advance_plane(kind, g, lap, cap, i, ny, nz, ds)
        else:
            for i in prange(nx):
                _laplacian_plane(kind, diff, g, lap, i, nx, ny, nz, periodic, ih2)
            for i in prange(nx):
                _advance_plane(kind, g, lap, cap, i, ny, nz, ds)
        if images:
            mirror_fluidity(fw, planes)
    return nsub


@njit(cache=True, error_model="numpy", inline="always")
def stress_ratio6(sxx, syy, szz, sxy, sxz, syz, p):
    """μ = τ̄/p with τ̄ = √(½ s:s) of the deviator s of σ; 0 if p ≤ 0."""
    m = (sxx + syy + szz) * THIRD
    a = sxx - m
    b = syy - m
    c = szz - m
    tau = math.sqrt(0.5 * (a * a + b * b + c * c) + sxy * sxy + sxz * sxz + syz * syz)
    return tau / p if p > 0.0 else 0.0


@njit(cache=True, error_model="numpy", parallel=True)
def _fluidity_g2p(P, fw, prm, mat, dt, nsub, serial):
    """The nodal increment of g back to the points (blended with a PIC share of the nodal
    value), then the local relaxation at each point with its own μ, p_e and d̄. In parallel, or
    in order on one thread (the same result without the region's cost)."""
    pr = prm[0]
    m0 = mat[0]
    ih = 1.0 / pr.h
    nx = pr.nodes[0]
    periodic = pr.periodic_x != 0
    x0 = pr.origin[0]
    y0 = pr.origin[1]
    z0 = pr.origin[2]
    law = (m0.rho_s, m0.mu_s, m0.t0, m0.ngf_b, m0.pfloor, m0.ds, m0.dl)  # no allocation per step
    x = P.x
    gf = P.gf
    phi = P.phi
    sig = P.sig
    pres = P.diag[0]
    if serial:
        for p in range(x.shape[1]):
            _fluidity_g2p_point(x, gf, phi, sig, pres, fw, ih, nx, periodic, x0, y0, z0, law,
                                dt, nsub, p)  # fmt: skip
    else:
        for p in prange(x.shape[1]):
            _fluidity_g2p_point(x, gf, phi, sig, pres, fw, ih, nx, periodic, x0, y0, z0, law,
                                dt, nsub, p)  # fmt: skip


@njit(cache=True, error_model="numpy", inline="always")
def _fluidity_g2p_point(x, gf, phi, sig, pres, fw, ih, nx, periodic, x0, y0, z0, law, dt, nsub,
                        p):  # fmt: skip
    """``_fluidity_g2p`` of the point ``p`` (``law`` = ρ_s, μ_s, t₀, b, p_floor, d_s, d_l)."""
    rho_s, mu_s, t0, b_, pfloor, ds, dl = law
    g = gf[p]
    if nsub > 0:
        bx, wx0, wx1, wx2, _, _, _, _ = bspline2_frac((x[0, p] - x0) * ih)
        by, wy0, wy1, wy2, _, _, _, _ = bspline2_frac((x[1, p] - y0) * ih)
        if D == 3:
            zp = x[2, p]
        else:
            zp = 0.0
        bz, wz0, wz1, wz2, _, _, _, _ = _z_axis(zp, z0, ih)
        wx = (wx0, wx1, wx2)
        wy = (wy0, wy1, wy2)
        wz = (wz0, wz1, wz2)
        dg = 0.0
        gi = 0.0
        wsum = 0.0
        for a in range(3):
            i = _wrap(bx + a, nx) if periodic else bx + a
            for b in range(3):
                j = by + b
                wab = wx[a] * wy[b]
                for c in range(SZ):
                    k = bz + c
                    if fw[W_KIND, i, j, k] != K_EMPTY:
                        w = wab * wz[c]
                        dg += w * (fw[W_G, i, j, k] - fw[W_G0, i, j, k])
                        gi += w * fw[W_G, i, j, k]
                        wsum += w
        g = g + dg
        if wsum > 0.0:
            g = (1.0 - PIC) * g + PIC * gi / wsum
        # a point diffused to (or below) zero keeps a tiny positive g, so that it is not
        # seeded again (only g = 0, material that never had fluidity, is seeded)
        g = max(TINY, g) if gf[p] > 0.0 else max(0.0, g)
    sxx, syy, szz, sxy, sxz, syz = _sym(sig, p)
    mu = stress_ratio6(sxx, syy, szz, sxy, sxz, syz, pres[p])
    dbar = phi[p] * ds + (1.0 - phi[p]) * dl
    gf[p] = relax_logistic(g, mu, pres[p], dbar, dt, rho_s, mu_s, t0, b_, pfloor)


@njit(cache=True, error_model="numpy")
def fluidity_step(P, G, prm, mat, dt):
    """Advance the fluidity of every point over ``dt`` (Lie splitting of
    t₀ ∂g/∂t = A² d̄² ∇²g − (μ_s − μ) g − b μ √(ρ_s d̄²/p) g²): nonlocal diffusion on the grid,
    then the exact local relaxation at the points. Returns the number of diffusion sub-steps."""
    fw = G.fw
    nsub = 0
    # one thread (the slab runs of P2G are sized for the call's thread count): the loops in
    # order, without the cost of parallel regions; the same result (not numba's
    # get_num_threads(), which would make the loop uncacheable)
    serial = G.bounds.shape[0] == 2
    if mat[0].ngf_a > 0.0:
        for f in (W_M, W_MG, W_MPHI):
            fw[f] = 0.0
        _fluidity_p2g(P, fw, prm)
        planes = fluidity_planes(prm)
        fold_fluidity(fw, planes)  # image nodes behind the zero-flux planes
        dmax = _fluidity_nodes(fw, prm, mat, serial)
        nsub = diffuse(fw, prm, dt, dmax, planes, serial)
    _fluidity_g2p(P, fw, prm, mat, dt, nsub, serial)
    return nsub


# ---------------------------------------------------------------------------------------------
# 6. segregation: the concentration step on the extra Eulerian grid (docs/segregation.md §2)

#: scratch arrays of ``concentration_step`` (first index of ``Segregation.work``)
(C_VOL, C_SUM_S, C_SUM_L, C_PHI, C_PHI0, C_S, C_GDOT, C_AX, C_BX, C_AY, C_BY, C_AZ, C_BZ,
 C_THETA, C_DIV, C_ACT, N_CWORK) = range(17)  # fmt: skip
#: cells a point's tent weights touch: 2 per axis
NCORNER = 8 if D == 3 else 4


@njit(cache=True, error_model="numpy", inline="always")
def _corners(px, py, pz, cgr, act, ci, cw):
    """A point's cells ``ci`` and tent weights ``cw`` (Σ = 1), restricted to the active cells and
    renormalised (docs/segregation.md §2, in D dimensions); the raw weights if none is
    active."""
    c = cgr[0]
    hc = c.hc
    i0, i1, wx0, wx1 = tent_weights(px, c.origin[0], hc, c.cells[0], c.periodic_x)
    j0, j1, wy0, wy1 = tent_weights(py, c.origin[1], hc, c.cells[1], 0)
    if D == 3:
        k0, k1, wz0, wz1 = tent_weights(pz, c.origin[2], hc, c.cells[2], 0)
    else:
        k0, k1, wz0, wz1 = 0, 0, 1.0, 0.0
    q = 0
    tot = 0.0
    for a in range(2):
        for b in range(2):
            for e in range(NCORNER // 4):
                ci[q, 0] = i0 if a == 0 else i1
                ci[q, 1] = j0 if b == 0 else j1
                ci[q, 2] = k0 if e == 0 else k1
                w = (wx0 if a == 0 else wx1) * (wy0 if b == 0 else wy1) * (wz0 if e == 0 else wz1)
                cw[q] = w
                tot += w * act[ci[q, 0], ci[q, 1], ci[q, 2]]
                q += 1
    if tot > 0.0:
        for q in range(NCORNER):
            cw[q] = cw[q] * act[ci[q, 0], ci[q, 1], ci[q, 2]] / tot


@njit(cache=True, error_model="numpy", inline="always")
def _face(sp, cell_a, cell_b, phic, sc, gc, hc, normal, flux_kind, d_s, d_l):
    """Rates (a, b) of the face from cell a to cell b (index triples) along ``normal``."""
    fa = phic[cell_a]
    fb = phic[cell_b]
    da = d_s * fa + d_l * (1.0 - fa)
    db = d_s * fb + d_l * (1.0 - fb)
    w, d = face_velocity_diffusivity(sp, sc[cell_a], sc[cell_b], gc[cell_a], gc[cell_b], da, db,
                                     hc, normal)  # fmt: skip
    return face_rates(w, d, hc, flux_kind)


@njit(cache=True, error_model="numpy")
def concentration_step(P, seg, t_int):
    """Advance φ_s of the points over one subcycle t_int (seed Fig. 1 i–k), in D dimensions:
    (i) points → cells with tent weights restricted to active cells (fill θ ≥ θ_min), (j) the
    closure's monotone face fluxes (x, y and, in 3-D, z faces) in explicit substeps, (k) the
    incremental bound-preserving mapping back. Conserves Σ V⁰ φ_s; keeps 0 ≤ φ_s ≤ 1. The same
    algorithm as the NumPy twin segregation.reference.concentration_step_ref. Returns the
    number of substeps."""
    sp = seg.prm
    x = P.x
    vol0 = P.vol0
    phi = P.phi
    s_int = P.s_int
    g_int = P.g_int
    n = x.shape[1]
    if int(sp[P_MODEL]) == M_NONE or not (t_int > 0.0):
        s_int[:] = 0.0
        g_int[:] = 0.0
        return 0
    wk = seg.work
    ci = seg.corner_cells
    cw = seg.corner_weights
    cg = seg.grid[0]
    hc = cg.hc
    ncx, ncy, ncz = cg.cells[0], cg.cells[1], cg.cells[2]
    per = cg.periodic_x
    cellvol = hc * hc * hc if D == 3 else hc * hc
    vol, sum_s, sum_l = wk[C_VOL], wk[C_SUM_S], wk[C_SUM_L]
    phic, phi0, sc, gc = wk[C_PHI], wk[C_PHI0], wk[C_S], wk[C_GDOT]
    theta, div, act = wk[C_THETA], wk[C_DIV], wk[C_ACT]
    # (i) pass 1: the raw fill decides the active cells
    vol[...] = 0.0
    act[...] = 1.0
    for p in range(n):
        _corners(x[0, p], x[1, p], x[2, p] if D == 3 else 0.0, seg.grid, act, ci, cw)
        for q in range(NCORNER):
            vol[ci[q, 0], ci[q, 1], ci[q, 2]] += cw[q] * vol0[p]
    for i in range(ncx):
        for j in range(ncy):
            for k in range(ncz):
                act[i, j, k] = 1.0 if vol[i, j, k] >= sp[P_FILL_MIN] * cellvol else 0.0
    vol[...] = 0.0
    sum_s[...] = 0.0
    sum_l[...] = 0.0
    sc[...] = 0.0
    gc[...] = 0.0
    # pass 2: the weights restricted to the active cells (the ones step (k) uses)
    for p in range(n):
        _corners(x[0, p], x[1, p], x[2, p] if D == 3 else 0.0, seg.grid, act, ci, cw)
        for q in range(NCORNER):
            c = (ci[q, 0], ci[q, 1], ci[q, 2])
            wv = cw[q] * vol0[p]
            vol[c] += wv
            sum_s[c] += wv * phi[p]
            sum_l[c] += wv * (1.0 - phi[p])
            sc[c] += wv * s_int[p]
            gc[c] += wv * g_int[p]
    for i in range(ncx):
        for j in range(ncy):
            for k in range(ncz):
                vc = vol[i, j, k]
                if vc > 0.0:
                    phic[i, j, k] = min(1.0, max(0.0, sum_s[i, j, k] / vc))
                    sc[i, j, k] /= vc * t_int
                    gc[i, j, k] /= vc * t_int
                else:
                    phic[i, j, k] = 0.0
                phi0[i, j, k] = phic[i, j, k]
                theta[i, j, k] = vc / cellvol
    # (j) face rates, frozen over the subcycle: face q of cell (i, j, k) to its + neighbour
    flux_kind = int(sp[P_FLUX])
    d_s = sp[P_D_SMALL]
    d_l = sp[P_D_LARGE]
    ra = (wk[C_AX], wk[C_AY], wk[C_AZ])
    rb = (wk[C_BX], wk[C_BY], wk[C_BZ])
    for q in range(D):
        ra[q][...] = 0.0
        rb[q][...] = 0.0
    for i in range(ncx):
        ib = i + 1
        if ib == ncx:
            ib = 0 if per == 1 else -1
        for j in range(ncy):
            for k in range(ncz):
                if act[i, j, k] == 0.0:
                    continue
                if ib >= 0 and ib != i and act[ib, j, k] > 0.0:
                    a, b = _face(sp, (i, j, k), (ib, j, k), phic, sc, gc, hc, 0, flux_kind,
                                 d_s, d_l)  # fmt: skip
                    ra[0][i, j, k] = a
                    rb[0][i, j, k] = b
                if j + 1 < ncy and act[i, j + 1, k] > 0.0:
                    a, b = _face(sp, (i, j, k), (i, j + 1, k), phic, sc, gc, hc, 1,
                                 flux_kind, d_s, d_l)  # fmt: skip
                    ra[1][i, j, k] = a
                    rb[1][i, j, k] = b
                if D == 3 and k + 1 < ncz and act[i, j, k + 1] > 0.0:
                    a, b = _face(seg.prm_z, (i, j, k), (i, j, k + 1), phic, sc, gc, hc, 0,
                                 flux_kind, d_s, d_l)  # fmt: skip
                    ra[2][i, j, k] = a
                    rb[2][i, j, k] = b
    # stable substep: Σ_faces max(a, b) ≤ θ_c h_c / Δt_c
    rate_max = 0.0
    bad = False
    for i in range(ncx):
        im = i - 1
        if im < 0:
            im = ncx - 1 if per == 1 else -1
        for j in range(ncy):
            for k in range(ncz):
                if act[i, j, k] == 0.0:
                    continue
                r = max(ra[0][i, j, k], rb[0][i, j, k]) + max(ra[1][i, j, k], rb[1][i, j, k])
                if im >= 0:
                    r += max(ra[0][im, j, k], rb[0][im, j, k])
                if j > 0:
                    r += max(ra[1][i, j - 1, k], rb[1][i, j - 1, k])
                if D == 3:
                    r += max(ra[2][i, j, k], rb[2][i, j, k])
                    if k > 0:
                        r += max(ra[2][i, j, k - 1], rb[2][i, j, k - 1])
                r /= theta[i, j, k] * hc
                if r != r:
                    bad = True
                elif r > rate_max:
                    rate_max = r
    nsub = 0
    if bad or not math.isfinite(rate_max):
        nsub = 1
    elif rate_max > 0.0:
        nsub = max(1, int(math.ceil(t_int * rate_max / sp[P_SAFETY])))
    dt = t_int / nsub if nsub > 0 else 0.0
    for _ in range(nsub):
        div[...] = 0.0
        for i in range(ncx):
            ib = i + 1
            if ib == ncx:
                ib = 0 if per == 1 else -1
            for j in range(ncy):
                for k in range(ncz):
                    fa = phic[i, j, k]
                    for q in range(D):
                        a = ra[q][i, j, k]
                        b = rb[q][i, j, k]
                        if a == 0.0 and b == 0.0:
                            continue
                        if q == 0:
                            if ib < 0:
                                continue
                            c = (ib, j, k)
                        elif q == 1:
                            c = (i, j + 1, k)
                        else:
                            c = (i, j, k + 1)
                        fb = phic[c]
                        flux = a * fa * (1.0 - fb) - b * fb * (1.0 - fa)
                        div[i, j, k] += flux
                        div[c] -= flux
        for i in range(ncx):
            for j in range(ncy):
                for k in range(ncz):
                    if div[i, j, k] != 0.0:
                        phic[i, j, k] -= dt * div[i, j, k] / (theta[i, j, k] * hc)
    # (k) cells → points, incremental and bound-preserving
    if nsub > 0:
        for i in range(ncx):
            for j in range(ncy):
                for k in range(ncz):
                    div[i, j, k] = phic[i, j, k] - phi0[i, j, k]
        for p in range(n):
            _corners(x[0, p], x[1, p], x[2, p] if D == 3 else 0.0, seg.grid, act, ci, cw)
            f = phi[p]
            dphi = 0.0
            for q in range(NCORNER):
                c = (ci[q, 0], ci[q, 1], ci[q, 2])
                dc = div[c]
                if dc > 0.0:
                    if sum_l[c] > 0.0:
                        dphi += cw[q] * dc * (1.0 - f) * vol[c] / sum_l[c]
                elif dc < 0.0:
                    if sum_s[c] > 0.0:
                        dphi += cw[q] * dc * f * vol[c] / sum_s[c]
            phi[p] = min(1.0, max(0.0, f + dphi))
    s_int[:] = 0.0
    g_int[:] = 0.0
    return nsub


# ---------------------------------------------------------------------------------------------
# 7. the column model (``scenario.solver = "column"``, 2-D only; docs/column.md): an x-uniform
#    layer as N two-node linear elements in depth, the elements the Points (their law, fluidity
#    and concentration steps the MPM's), the nodes a (COL_ROWS, N + 1) array of rows COL_*


@njit(cache=True, error_model="numpy")
def column_time_step(prm, clk, nodes):
    """Δt = min(C Δy/(max(c + |v|) + 2 ν_max/Δy), C_ν Δy²/(2 ν_max), Δt_max) on the shortest
    element Δy: the combined wave and diffusion bound of the explicit 1-D scheme (C =
    ``time.column_courant`` in ``prm.cfl``; each limit alone was unstable, docs/column.md)."""
    pr = prm[0]
    dymin = math.inf
    for e in range(nodes.shape[1] - 1):
        dymin = min(dymin, nodes[COL_Y, e + 1] - nodes[COL_Y, e])
    dt = pr.dt_max
    smax = max(clk.smax, pr.c_floor)
    rate = smax + 2.0 * clk.numax / dymin
    if rate > 0.0:
        dt = min(dt, pr.cfl * dymin / rate)
    if clk.numax > 0.0:
        dt = min(dt, pr.visc * dymin * dymin / (2.0 * clk.numax))
    return dt


@njit(cache=True, error_model="numpy")
def column_nodes(nodes, P, prm, dt, ramp):
    """The nodal velocities over one step: the internal force l_x (σ_above − σ_below) (zero
    traction above the top node; l_x the column's width in x), gravity, the 2-D sidewall force
    on Σ V p of the node's half elements, then the boundary planes (the base) on node 0."""
    pr = prm[0]
    lx = pr.length_x
    gx = pr.gravity[0] * ramp
    gy = pr.gravity[1]
    sw = pr.sidewall * ramp
    uw = pr.sidewall_speed
    sw0 = pr.sidewall_slow * ramp if uw > 0.0 else sw
    sig = P.sig
    vol0 = P.vol0
    J = P.J
    pres = P.diag[0]
    ne = nodes.shape[1] - 1
    for j in range(1, ne):
        b = j - 1
        vp = 0.5 * vol0[j] * J[j] * pres[j] + 0.5 * vol0[b] * J[b] * pres[b]
        node_velocity(j, sig[XY, j] - sig[XY, b], sig[YY, j] - sig[YY, b], vp, nodes, dt, gx, gy,
                     sw, sw0, uw, lx)  # fmt: skip
    b = ne - 1
    node_velocity(ne, -sig[XY, b], -sig[YY, b], 0.5 * vol0[b] * J[b] * pres[b], nodes, dt, gx, gy,
                 sw, sw0, uw, lx)  # fmt: skip
    node_velocity(0, sig[XY, 0], sig[YY, 0], 0.5 * vol0[0] * J[0] * pres[0], nodes, dt, gx, gy,
                 sw, sw0, uw, lx)  # fmt: skip
    vx, vy, _ = apply_planes(prm, 0.5 * lx, nodes[COL_Y, 0], 0.0, nodes[COL_U, 0],
                             nodes[COL_V, 0], 0.0)  # fmt: skip
    nodes[COL_U, 0] = vx
    nodes[COL_V, 0] = vy


@njit(cache=True, error_model="numpy")
def column_kinematics(nodes, P, dt):
    """Each element's velocity gradient L = [[0, ∂u/∂y], [0, ∂v/∂y]] (``P.lg``), its
    J ← J (1 + Δt ∂v/∂y) and its velocity, the mean of its nodes'."""
    lg = P.lg
    J = P.J
    v = P.v
    for e in range(J.shape[0]):
        dy = nodes[COL_Y, e + 1] - nodes[COL_Y, e]
        u0 = nodes[COL_U, e]
        u1 = nodes[COL_U, e + 1]
        w0 = nodes[COL_V, e]
        w1 = nodes[COL_V, e + 1]
        l11 = (w1 - w0) / dy
        lg[0, e] = 0.0
        lg[1, e] = (u1 - u0) / dy
        lg[D, e] = 0.0
        lg[D + 1, e] = l11
        J[e] = J[e] * (1.0 + dt * l11)
        v[0, e] = 0.5 * (u0 + u1)
        v[1, e] = 0.5 * (w0 + w1)


@njit(cache=True, error_model="numpy")
def column_positions(nodes, P, dt):
    """Node positions y ← y + Δt v, then the elements' centres."""
    for j in range(nodes.shape[1]):
        nodes[COL_Y, j] += dt * nodes[COL_V, j]
    x = P.x
    for e in range(x.shape[1]):
        x[1, e] = 0.5 * (nodes[COL_Y, e] + nodes[COL_Y, e + 1])


# ---------------------------------------------------------------------------------------------
# the step: the material pass and the time loop, compiled once per law
#
# ``codegen`` writes the section below, from the line STEP_SECTION on, into a file of its own per
# law (``kernels_d2_law1.py`` …), run in a namespace that holds everything above, and with the
# line ``LAW = …`` set. A run compiles only its own law: the law is a compile-time constant of
# ``update_stress`` and ``advance``, and the kernels above are compiled and cached once whatever
# the law (docs/architecture.md, docs/performance.md).

STEP_SECTION = True
#: the constitutive law of this copy (``LAW_*``; set by the code generator)
LAW = LAW_FEI


@njit(cache=True, error_model="numpy", inline="always")
def _tick(clk, t, dt, smax, numax):
    """The clock after a step Δt from t: time, step count, Δt, the segregation subcycle's
    elapsed time, and the wave speed and viscosity the next step's Δt is taken from."""
    clk.time = t + dt
    clk.step += 1
    clk.dt = dt
    clk.tseg += dt
    clk.smax = smax
    clk.numax = numax


@njit(cache=True, error_model="numpy", parallel=True, fastmath={"contract"})
def update_stress(P, mat, dt, full, threads):
    """The material law at every point from ``P.lg`` (L of G2P), the subcycle integrals and the
    step check. Returns (status, first failing point or −1, max c + |v|, max ν); the failing point
    is the first in index order (a min-reduction), independent of the thread count. The output
    diagnostics (``diag`` rows 1–5) are written when ``full`` and for a failing point.

    Blocks of points in parallel; in each, the update loop with the law of this copy (``LAW``,
    a compile-time constant: :func:`_stress_block`, vectorised) and then a short scalar reduction
    (``engine.helpers._reduce_block``: the largest c + |v| and ν, the first failing point, the
    diagnostics of every point if ``full``, else of the failing ones).
    ``threads`` only sets the block size (at least two blocks per thread); no result depends on
    it."""
    diag = P.diag
    n = P.x.shape[1]
    size = max(8, min(BLOCK, 8 * ((n + 16 * threads - 1) // (16 * threads))))
    smax = 0.0
    numax = 0.0
    bad = n
    for blk in prange((n + size - 1) // size):
        lo = blk * size
        m = min(size, n - lo)
        buf = np.empty((B_ROWS, size))
        _stress_block(LAW, lo, m, buf, P, mat, dt)
        bs, bn, bb = _reduce_block(lo, m, n, buf, diag, full)
        smax = max(smax, bs)
        numax = max(numax, bn)
        bad = min(bad, bb)
    return _pass_status(P, bad, smax, numax)


@njit(cache=True, error_model="numpy", inline="always")
def _pass_status(P, bad, smax, numax):
    """The result of a material pass: (status, first failing point or −1, max c + |v|, max ν);
    a failing point whose state is not finite reports ST_NONFINITE."""
    n = P.J.shape[0]
    if bad >= n:
        return ST_OK, -1, smax, numax
    ok_state = math.isfinite(P.diag[4, bad]) and P.J[bad] > 0.0
    for a in range(D):
        ok_state = ok_state and math.isfinite(P.x[a, bad])
    for a in range(NE):
        ok_state = ok_state and math.isfinite(P.sig[a, bad])
    return (P.flags[bad] if ok_state else ST_NONFINITE), bad, smax, numax


@njit(cache=True, error_model="numpy", parallel=True, fastmath={"contract"})
def column_stress(P, mat, dt, full, buf):
    """The material pass of the column: :func:`update_stress` as one block (``buf``: B_ROWS × N,
    allocated once per call of the loop) in a one-block parallel region, the reduction after
    it. The same results; for the column's ~150 elements the blocked pass's per-call cost (its
    buffers and parallel reductions: ``benchmarks/column_pass.py``) was twice the work."""
    n = P.J.shape[0]
    for _ in prange(1):  # the region lets LLVM vectorise the block (docs/column.md)
        _stress_block(LAW, 0, n, buf, P, mat, dt)
    smax, numax, bad = _reduce_block(0, n, n, buf, P.diag, full)
    return _pass_status(P, bad, smax, numax)


@njit(cache=True, error_model="numpy")
def prime(P, mat):
    """Stress, diagnostics and wave speeds of the initial state (no deformation, Δt = 0)."""
    P.lg[:, :] = 0.0
    P.flags[:] = ST_OK
    s = P.s_int.copy()
    g = P.g_int.copy()
    # the argument types of the call in advance (bool, int64), not the literals True and 1:
    # a literal argument would compile a second copy of the pass (docs/performance.md)
    one = np.int64(1)
    update_stress(P, mat, 0.0, one > 0, one)
    P.s_int[:] = s
    P.g_int[:] = g


@njit(cache=True, error_model="numpy")
def time_step(prm, clk):
    """Δt = min(C_cfl h / max(c + |v|, c_floor), visc h² / (2 ν_max), Δt_max)."""
    pr = prm[0]
    dt = pr.dt_max
    smax = max(clk.smax, pr.c_floor)
    if smax > 0.0:
        dt = min(dt, pr.cfl * pr.h / smax)
    if clk.numax > 0.0:
        dt = min(dt, pr.visc * pr.h * pr.h / (2.0 * clk.numax))
    return dt


@njit(cache=True, error_model="numpy")
def advance(P, G, prm, mat, clock, seg, t_stop, max_steps):
    """Advance to ``t_stop`` (exactly) or by ``max_steps`` steps. Returns (status, point, steps).

    The whole step, in order (the module docstring numbers them)."""
    clk = clock[0]
    nslabs = G.slab_start.shape[0] - 1
    threads = G.bounds.shape[0] - 1
    planes = image_planes(prm)
    musl = prm[0].transfer == TRANSFER_FLIP
    steps = 0
    while steps < max_steps and clk.time < t_stop:
        t = clk.time
        dt = time_step(prm, clk)
        if dt < prm[0].dt_min:
            return ST_DT_COLLAPSE, -1, steps
        last = steps + 1 >= max_steps
        if t + dt * 1.000001 >= t_stop:
            dt = t_stop - t
            last = True
        tr = prm[0].ramp
        ramp = min(1.0, (t + dt) / tr) if tr > 0.0 else 1.0

        if steps == 0:
            slab_index(P, prm, nslabs)  # 1. sort (G2P keeps the slabs afterwards)
        counting_sort(P.cursor, G.slab_start, G.order, threads)
        p2g(P, G, prm, False)  # 2. P2G
        fold_images(G, planes, prm, ramp)  #    image nodes behind the walls
        grid_update(G, prm, dt, ramp)  # 3. grid update, boundaries
        mirror_images(G, planes)
        if musl:
            P.x_old[:, :] = P.x
        g2p(P, G, prm, dt, nslabs)  # 4. G2P, advection
        if musl:  # 4a. MUSL: remap the new momenta (old positions), L from them, then J
            p2g(P, G, prm, True)
            fold_images(G, planes, prm, 0.0)
            momentum_to_velocity(G, prm)
            mirror_images(G, planes)
            musl_gradient(P, G, prm, dt)
        if prm[0].dilatation != 0:
            smooth_dilatation(P, G, prm, dt)  #    volumetric smoothing of L, then J
        status, idx, smax, numax = update_stress(P, mat, dt, last, threads)  # 5. material law

        _tick(clk, t, dt, smax, numax)
        steps += 1
        if status != ST_OK:
            return status, idx, steps
        if LAW == LAW_NGF:  # 5b. fluidity update, every material.fluidity_dt (NGF only)
            clk.tflu += dt
            if clk.tflu >= mat[0].flu_dt * (1.0 - 1e-12):
                fluidity_step(P, G, prm, mat, clk.tflu)
                clk.nflu += 1
                clk.tflu = 0.0
        if clk.tseg >= seg.prm[P_DT_TARGET] * (1.0 - 1e-12):  # 6. segregation subcycle
            concentration_step(P, seg, clk.tseg)
            clk.nseg += 1
            clk.tseg = 0.0
    return ST_OK, -1, steps


@njit(cache=True, error_model="numpy")
def advance_column(P, Pc, nodes, G, prm, mat, clock, seg, t_stop, max_steps):
    """The column model's time loop (``scenario.solver = "column"``, 2-D; docs/column.md), with
    the contract of :func:`advance`. ``P``: the elements; ``Pc``: the same arrays with ``vol0``
    the elements' volumes on the concentration grid's one-cell width; ``G.fw``: the
    one-node-wide periodic fluidity grid. The order of the MPM's update-stress-last step:"""
    clk = clock[0]
    n = P.J.shape[0]
    pr = prm[0]
    y_max = pr.origin[1] + (pr.nodes[1] - 1.5) * pr.h
    buf = np.empty((B_ROWS, n))  # the material pass's block buffer
    steps = 0
    while steps < max_steps and clk.time < t_stop:
        t = clk.time
        dt = column_time_step(prm, clk, nodes)
        if not (dt >= pr.dt_min):
            return ST_DT_COLLAPSE, -1, steps
        last = steps + 1 >= max_steps
        if t + dt * 1.000001 >= t_stop:
            dt = t_stop - t
            last = True
        ramp = min(1.0, (t + dt) / pr.ramp) if pr.ramp > 0.0 else 1.0

        column_nodes(nodes, P, prm, dt, ramp)  # 1. nodal forces, velocities, the base
        column_kinematics(nodes, P, dt)  # 2. element L, J and velocity
        status, idx, smax, numax = column_stress(P, mat, dt, last, buf)  # 3. material law
        column_positions(nodes, P, dt)  # 4. node positions

        _tick(clk, t, dt, smax, numax)
        steps += 1
        if status != ST_OK:
            return status, idx, steps
        if not (nodes[COL_Y, n] < y_max):
            return (ST_LEFT_GRID if math.isfinite(nodes[COL_Y, n]) else ST_NONFINITE), n - 1, steps
        if LAW == LAW_NGF:  # 5. fluidity update on the one-node-wide grid
            clk.tflu += dt
            if clk.tflu >= mat[0].flu_dt * (1.0 - 1e-12):
                fluidity_step(P, G, prm, mat, clk.tflu)
                clk.nflu += 1
                clk.tflu = 0.0
        if clk.tseg >= seg.prm[P_DT_TARGET] * (1.0 - 1e-12):  # 6. segregation subcycle
            if seg.prm[P_MODEL] != 0.0:
                concentration_step(Pc, seg, clk.tseg)
                clk.nseg += 1
            else:
                P.s_int[:] = 0.0
                P.g_int[:] = 0.0
            clk.tseg = 0.0
    return ST_OK, -1, steps


__all__ = ["D", "NE", "NF", "NV", "NW", "SLAB", "advance", "advance_column", "apply_planes", "column_stress", "fei_tensor",
           "fluidity_step", "g2p", "grid_update", "ngf_tensor", "p2g", "prime", "update_stress"]  # fmt: skip
