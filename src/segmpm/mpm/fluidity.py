"""The fluidity update of the nonlocal rheology: nonlocal diffusion on the MPM grid, then the
local relaxation at the material points (docs/model.md, "Nonlocal rheology").

The fluidity g is carried by the material points (``State.gf``; it moves with the material, like
φ_s). Every ``material.fluidity_dt`` of simulated time the engine calls :func:`fluidity_step`
with the time Δt_g since the last call, which splits the dynamic equation

    t₀ ∂g/∂t = A² d̄² ∇²g − (μ_s − μ) g − b μ √(ρ_s d̄²/p) g²

into (Lie splitting)

1. **diffusion** ∂g/∂t = (A² d̄²/t₀) ∇²g on the grid nodes: P2G of m g and m φ with the
   B-spline weights (nodal g = Σ w m g / Σ w m, d̄ from the nodal φ), explicit five-point
   finite differences in sub-steps below the stability limit h²/(4 D_max), and G2P of the nodal
   *increment* blended with a small share ``PIC`` of the nodal value (FLIP-like, so the transfer
   adds little smoothing of its own, while the point-scale modes are damped);
2. **local relaxation** at each point with its own μ (from σ), p_e and d̄: the exact solution of
   the logistic equation for μ and p frozen over Δt_g (``materials.ngf.relax_local``).

Boundary conditions (grid nodes): the free surface is a cut cell: a node's P2G mass fraction
gives the filled part c of its control volume, which is its capacity in the finite-volume
update, and the zero-flux (∂g/∂n = 0) face lies between the last node with material in its
control volume and the first empty one. Nodes at and beyond a no-slip (rough) base
or wall are Dirichlet nodes with g = 0 (Henann & Kamrin 2013; Haeri & Skonieczny 2022); slip and
friction walls are zero-flux. Disconnected material (p ≤ 0, gas) has g = 0.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..materials.ngf import SEED_FRACTION, relax_local, stress_ratio
from ..materials.params import M_DL, M_DS, M_F, M_NGF_A, M_RHO_S, M_T0
from .params import (
    BC_NOSLIP,
    G_BASE_KIND,
    G_BASE_Y,
    G_H,
    G_PERIODIC,
    G_X0,
    G_XHI,
    G_XHI_KIND,
    G_XLO,
    G_XLO_KIND,
    G_Y0,
)
from .shape import bspline2_frac

#: fields of the fluidity work array ``fw`` (NF_FIELDS, N_x, N_y)
F_M, F_MG, F_MPHI, F_G, F_G0, F_LAP, F_KIND, NF_FIELDS = range(8)

#: node kinds (``fw[F_KIND]``)
K_EMPTY, K_ACTIVE, K_DIRICHLET = 0.0, 1.0, 2.0

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

__all__ = ["F_G", "F_KIND", "NF_FIELDS", "SEED_FRACTION", "allocate", "fluidity_step"]


def allocate(nx: int, ny: int) -> np.ndarray:
    """The work array ``fw`` of :func:`fluidity_step` for an N_x × N_y grid."""
    return np.zeros((NF_FIELDS, nx, ny))


@njit(cache=True, error_model="numpy", inline="always")
def _wrap(i, n):
    """Periodic index of a stencil node (i ∈ [−1, n + 1]); a grid of one or two nodes in x
    (the column model's) wraps more than once."""
    while i < 0:
        i += n
    while i >= n:
        i -= n
    return i


@njit(cache=True, error_model="numpy")
def _node_kinds(fw, gp, mp):
    """Nodal g (from the P2G sums), the node kinds and capacities; returns the largest
    D/c = A² d̄²/(t₀ c) (the explicit stability limit)."""
    nx = fw.shape[1]
    ny = fw.shape[2]
    h = gp[G_H]
    tol = 1e-9 * h
    m_full = mp[M_F] * mp[M_RHO_S] * h * h
    coef = mp[M_NGF_A] ** 2 / mp[M_T0]
    base_rough = int(gp[G_BASE_KIND]) == BC_NOSLIP
    closed = gp[G_PERIODIC] == 0.0
    lo_rough = closed and int(gp[G_XLO_KIND]) == BC_NOSLIP
    hi_rough = closed and int(gp[G_XHI_KIND]) == BC_NOSLIP
    dmax = 0.0
    for i in range(nx):
        xn = gp[G_X0] + i * h
        for j in range(ny):
            yn = gp[G_Y0] + j * h
            m = fw[F_M, i, j]
            g = 0.0
            cap = min(1.0, max(0.0, FILL_SLOPE * m / m_full - FILL_OFFSET))
            kind = K_ACTIVE if cap > 0.0 else K_EMPTY
            if (
                (base_rough and yn <= gp[G_BASE_Y] + tol)
                or (lo_rough and xn <= gp[G_XLO] + tol)
                or (hi_rough and xn >= gp[G_XHI] - tol)
            ):
                kind = K_DIRICHLET
            fw[F_LAP, i, j] = 0.0
            if kind == K_ACTIVE:
                g = fw[F_MG, i, j] / m
                phi = min(1.0, max(0.0, fw[F_MPHI, i, j] / m))
                d = phi * mp[M_DS] + (1.0 - phi) * mp[M_DL]
                # the diffusivity A² d̄²/t₀ of the node, kept in the Laplacian slot until used
                fw[F_LAP, i, j] = coef * d * d
                dmax = max(dmax, fw[F_LAP, i, j] / max(cap, CAPACITY_MIN))
            # the capacity, kept in the φ slot (no longer needed)
            fw[F_MPHI, i, j] = max(cap, CAPACITY_MIN) if kind == K_ACTIVE else 0.0
            fw[F_KIND, i, j] = kind
            fw[F_G, i, j] = g
            fw[F_G0, i, j] = g
    return dmax


@njit(cache=True, error_model="numpy")
def _diffuse(fw, gp, dt, dmax):
    """Explicit five-point finite-volume diffusion of the nodal g over ``dt`` (sub-stepped):
    c_i ∂g_i/∂t = Σ_faces D_f (g_j − g_i)/h² with the capacity c_i of the node (``_node_kinds``);
    returns the number of sub-steps. Face diffusivity: the mean of the two nodes' (the active
    node's at a Dirichlet neighbour); no flux into empty nodes."""
    if not (dmax > 0.0) or not (dt > 0.0):
        return 0
    nx = fw.shape[1]
    ny = fw.shape[2]
    h = gp[G_H]
    ih2 = 1.0 / (h * h)
    periodic = gp[G_PERIODIC] != 0.0
    nsub = max(1, int(math.ceil(dt * 4.0 * dmax * ih2 / SAFETY)))
    ds = dt / nsub
    dcoef = fw[F_M]  # the P2G mass is no longer needed: it holds the node diffusivity
    for i in range(nx):
        for j in range(ny):
            dcoef[i, j] = fw[F_LAP, i, j] if fw[F_KIND, i, j] == K_ACTIVE else 0.0
    lap = fw[F_LAP]
    g = fw[F_G]
    kind = fw[F_KIND]
    # a one-node-wide periodic grid (the column model) has no x-neighbours but the node itself
    q0 = 2 if (periodic and nx == 1) else 0
    for _ in range(nsub):
        for i in range(nx):
            for j in range(ny):
                lap[i, j] = 0.0
                if kind[i, j] != K_ACTIVE:
                    continue
                di = dcoef[i, j]
                gi = g[i, j]
                acc = 0.0
                for q in range(q0, 4):
                    if q == 0:
                        a, b = i - 1, j
                    elif q == 1:
                        a, b = i + 1, j
                    elif q == 2:
                        a, b = i, j - 1
                    else:
                        a, b = i, j + 1
                    if b < 0 or b >= ny:
                        continue
                    if periodic:
                        a = _wrap(a, nx)
                    elif a < 0 or a >= nx:
                        continue
                    k = kind[a, b]
                    if k == K_ACTIVE:
                        acc += 0.5 * (di + dcoef[a, b]) * (g[a, b] - gi)
                    elif k == K_DIRICHLET:
                        acc -= di * gi
                lap[i, j] = acc * ih2
        for i in range(nx):
            for j in range(ny):
                if kind[i, j] == K_ACTIVE:
                    g[i, j] += ds * lap[i, j] / fw[F_MPHI, i, j]
    return nsub


@njit(cache=True, error_model="numpy")
def fluidity_step(x, mass, phi, sig, pres, gf, gp, mp, fw, dt):
    """Advance the fluidity ``gf`` of every point over ``dt`` (module docstring); returns the
    number of diffusion sub-steps. ``pres``: p_e of the points (``diag[0]``)."""
    n = x.shape[1]
    nx = fw.shape[1]
    ny = fw.shape[2]
    h = gp[G_H]
    ih = 1.0 / h
    x0 = gp[G_X0]
    y0 = gp[G_Y0]
    periodic = gp[G_PERIODIC] != 0.0
    for f in (F_M, F_MG, F_MPHI):
        for i in range(nx):
            for j in range(ny):
                fw[f, i, j] = 0.0
    nonlocal_on = mp[M_NGF_A] > 0.0
    if nonlocal_on:
        for p in range(n):
            bx, wx0, wx1, wx2, _, _, _, _ = bspline2_frac((x[0, p] - x0) * ih)
            by, wy0, wy1, wy2, _, _, _, _ = bspline2_frac((x[1, p] - y0) * ih)
            m = mass[p]
            mg = m * gf[p]
            mf = m * phi[p]
            for a in range(3):
                wa = wx0 if a == 0 else (wx1 if a == 1 else wx2)
                i = _wrap(bx + a, nx) if periodic else bx + a
                for b in range(3):
                    w = wa * (wy0 if b == 0 else (wy1 if b == 1 else wy2))
                    j = by + b
                    fw[F_M, i, j] += w * m
                    fw[F_MG, i, j] += w * mg
                    fw[F_MPHI, i, j] += w * mf
        dmax = _node_kinds(fw, gp, mp)
        nsub = _diffuse(fw, gp, dt, dmax)
    else:
        nsub = 0
    ds = mp[M_DS]
    dl = mp[M_DL]
    for p in range(n):
        g = gf[p]
        if nonlocal_on and nsub > 0:
            bx, wx0, wx1, wx2, _, _, _, _ = bspline2_frac((x[0, p] - x0) * ih)
            by, wy0, wy1, wy2, _, _, _, _ = bspline2_frac((x[1, p] - y0) * ih)
            dg = 0.0
            gi = 0.0
            wsum = 0.0
            for a in range(3):
                wa = wx0 if a == 0 else (wx1 if a == 1 else wx2)
                i = _wrap(bx + a, nx) if periodic else bx + a
                for b in range(3):
                    j = by + b
                    if fw[F_KIND, i, j] != K_EMPTY:
                        w = wa * (wy0 if b == 0 else (wy1 if b == 1 else wy2))
                        dg += w * (fw[F_G, i, j] - fw[F_G0, i, j])
                        gi += w * fw[F_G, i, j]
                        wsum += w
            g = g + dg
            if wsum > 0.0:
                # a small PIC share damps the point-scale modes the grid cannot see
                g = (1.0 - PIC) * g + PIC * gi / wsum
            # a point diffused to (or below) zero keeps a tiny positive g, so that it is not
            # seeded again (``relax_local`` seeds only g = 0: material that never had fluidity)
            g = max(TINY, g) if gf[p] > 0.0 else max(0.0, g)
        mu = stress_ratio(sig[0, p], sig[1, p], sig[2, p], sig[3, p], pres[p])
        dbar = phi[p] * ds + (1.0 - phi[p]) * dl
        gf[p] = relax_local(g, mu, pres[p], dbar, dt, mp)
    return nsub


# ---------------------------------------------------------------------------------------------
# NumPy reference (the same scheme, written with arrays)


def fluidity_step_np(x, mass, phi, sig, pres, gf, gp, mp, dt):
    """NumPy twin of :func:`fluidity_step` (nodes and points as arrays); returns the new g of the
    points and the number of diffusion sub-steps."""
    from ..materials.ngf import local_fluidity_np, relax_local_np, stress_ratio_np  # noqa: F401
    from .params import G_NX, G_NY
    from .shape import bspline2_np

    nx, ny = int(gp[G_NX]), int(gp[G_NY])
    h = gp[G_H]
    periodic = gp[G_PERIODIC] != 0.0
    gnew = np.array(gf, dtype=np.float64)
    nsub = 0
    if mp[M_NGF_A] > 0:
        bxs, wx, _ = bspline2_np((x[0] - gp[G_X0]) / h)
        bys, wy, _ = bspline2_np((x[1] - gp[G_Y0]) / h)
        I = bxs[:, None, None] + np.arange(3)[None, :, None]
        Jn = bys[:, None, None] + np.arange(3)[None, None, :]
        if periodic:
            I = I % nx
        I = np.broadcast_to(I, (len(bxs), 3, 3))
        Jn = np.broadcast_to(Jn, (len(bxs), 3, 3))
        W = wx[:, :, None] * wy[:, None, :]
        M = np.zeros((nx, ny))
        MG = np.zeros((nx, ny))
        MF = np.zeros((nx, ny))
        np.add.at(M, (I, Jn), W * mass[:, None, None])
        np.add.at(MG, (I, Jn), W * (mass * gf)[:, None, None])
        np.add.at(MF, (I, Jn), W * (mass * phi)[:, None, None])
        m_full = mp[M_F] * mp[M_RHO_S] * h * h
        cap = np.clip(FILL_SLOPE * M / m_full - FILL_OFFSET, 0.0, 1.0)
        active = cap > 0
        with np.errstate(invalid="ignore", divide="ignore"):
            g = np.where(active, MG / np.where(active, M, 1), 0.0)
            ph = np.clip(np.where(active, MF / np.where(active, M, 1), 0.0), 0, 1)
        d = ph * mp[M_DS] + (1 - ph) * mp[M_DL]
        D = np.where(active, mp[M_NGF_A] ** 2 / mp[M_T0] * d * d, 0.0)
        xn = gp[G_X0] + np.arange(nx)[:, None] * h + 0 * np.arange(ny)[None, :]
        yn = gp[G_Y0] + np.arange(ny)[None, :] * h + 0 * np.arange(nx)[:, None]
        tol = 1e-9 * h
        dirichlet = np.zeros((nx, ny), dtype=bool)
        if int(gp[G_BASE_KIND]) == BC_NOSLIP:
            dirichlet |= yn <= gp[G_BASE_Y] + tol
        if not periodic:
            if int(gp[G_XLO_KIND]) == BC_NOSLIP:
                dirichlet |= xn <= gp[G_XLO] + tol
            if int(gp[G_XHI_KIND]) == BC_NOSLIP:
                dirichlet |= xn >= gp[G_XHI] - tol
        active &= ~dirichlet
        g[dirichlet] = 0.0
        D[dirichlet] = 0.0
        g0 = g.copy()
        capf = np.maximum(cap, CAPACITY_MIN)
        dmax = (D / capf)[active].max() if active.any() else 0.0
        if dmax > 0 and dt > 0:
            nsub = max(1, int(math.ceil(dt * 4 * dmax / h**2 / SAFETY)))
            ds = dt / nsub
            for _ in range(nsub):
                lap = np.zeros((nx, ny))
                for di, dj in ((-1, 0), (1, 0), (0, -1), (0, 1)):
                    gs = np.roll(g, (-di, -dj), axis=(0, 1))
                    Ds = np.roll(D, (-di, -dj), axis=(0, 1))
                    As = np.roll(active, (-di, -dj), axis=(0, 1))
                    Ks = np.roll(dirichlet, (-di, -dj), axis=(0, 1))
                    valid = np.ones((nx, ny), dtype=bool)
                    if dj == 1:
                        valid[:, -1] = False
                    if dj == -1:
                        valid[:, 0] = False
                    if not periodic and di == 1:
                        valid[-1, :] = False
                    if not periodic and di == -1:
                        valid[0, :] = False
                    lap += np.where(valid & As, 0.5 * (D + Ds) * (gs - g), 0.0)
                    lap += np.where(valid & Ks, -D * g, 0.0)
                g = g + ds * np.where(active, lap / (h**2 * capf), 0.0)
            inc = np.where(active, g - g0, 0.0)
            seen = active | dirichlet
            Wk = W * seen[I, Jn]
            wsum = Wk.sum(axis=(1, 2))
            gflip = gnew + np.sum(W * inc[I, Jn], axis=(1, 2))
            with np.errstate(invalid="ignore", divide="ignore"):
                gpic = np.sum(Wk * np.where(seen, g, 0.0)[I, Jn], axis=(1, 2)) / np.where(
                    wsum > 0, wsum, 1
                )
            gb = np.where(wsum > 0, (1 - PIC) * gflip + PIC * gpic, gflip)
            gnew = np.where(np.asarray(gf) > 0, np.maximum(TINY, gb), np.maximum(0.0, gb))
    mu = stress_ratio_np(sig, pres)
    dbar = phi * mp[M_DS] + (1 - phi) * mp[M_DL]
    return relax_local_np(gnew, mu, pres, dbar, dt, mp), nsub
