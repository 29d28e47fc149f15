"""NumPy reference of the fluidity update of the nonlocal rheology (the twin the engine's
compiled ``fluidity_step`` is tested against, tests/test_nonlocal.py), in the layout of
segmpm.mpm.params: nonlocal diffusion on the MPM grid, then the
local relaxation at the material points (docs/model.md, "Nonlocal rheology").

The fluidity g is carried by the material points (``gf``; it moves with the material, like
φ_s). Every ``material.fluidity_dt`` of simulated time the engine calls its fluidity step
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

from ..engine.helpers import CAPACITY_MIN, FILL_OFFSET, FILL_SLOPE, PIC, SAFETY, TINY
from ..engine.shape import bspline2_np
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


def fluidity_step_np(x, mass, phi, sig, pres, gf, gp, mp, dt):
    """NumPy twin of the engine's 2-D fluidity step (nodes and points as arrays); returns the new g of the
    points and the number of diffusion sub-steps."""
    from ..materials.ngf import local_fluidity_np, relax_local_np, stress_ratio_np  # noqa: F401
    from .params import G_NX, G_NY

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
