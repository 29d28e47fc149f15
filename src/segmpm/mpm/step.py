"""The compiled time loop: ``advance`` runs P2G → grid update → G2P → stress update (USL) →
segregation sub-step, until a target time or a step budget, without returning to Python.

The time step is recomputed every step from the current state (physics.md §5.5):
Δt = min(C_cfl h / max_p(c_p + |v_p|), C_cfl h² / (2 max_p ν_p), Δt_max).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from ..materials import material_update
from ..segregation.closures import P_DT_TARGET, P_MODEL
from ..segregation.grid import concentration_step
from .params import (
    G_CFL,
    G_DTMAX,
    G_DTMIN,
    G_FLIP,
    G_H,
    G_LX,
    G_NX,
    G_NY,
    G_PERIODIC,
    G_RAMP,
    G_TRANSFER,
    G_X0,
    G_Y0,
    S_DT,
    S_NSEG,
    S_NUMAX,
    S_SMAX,
    S_STEP,
    S_TIME,
    S_TSEG,
    ST_DT_COLLAPSE,
    ST_LEFT_GRID,
    ST_NONFINITE,
    ST_OK,
    TRANSFER_AFLIP,
    TRANSFER_FLIP,
)
from .transfer import (
    gather_old,
    gather_point,
    grid_update,
    momentum_to_velocity,
    p2g,
    sort_into_strips,
)


@njit(cache=True, inline="always")
def _inside(gp, xp, yp):
    """True if the point's 3×3 stencil lies inside the grid."""
    h = gp[G_H]
    xi = (yp - gp[G_Y0]) / h
    if not (xi >= 0.5 and xi < gp[G_NY] - 1.5):
        return False
    if gp[G_PERIODIC] == 0.0:
        xi = (xp - gp[G_X0]) / h
        if not (xi >= 0.5 and xi < gp[G_NX] - 1.5):
            return False
    return True


@njit(cache=True, parallel=True)
def update_points(x, v, C, J, eps, sig, phi, diag, s_int, g_int, gp, mp, gv, gv_old, dt, flags):
    """G2P (APIC, or the FLIP/PIC blend of MUSL), advection, J, and the material update.

    ``diag`` (6, N): pressure, shear rate, inertial number, driver S, c + |v|, ν.
    ``flags[p]``: 0 ok, ST_NONFINITE or ST_LEFT_GRID.
    """
    n = x.shape[1]
    flip = gp[G_TRANSFER] == TRANSFER_FLIP
    aflip = gp[G_TRANSFER] == TRANSFER_AFLIP
    alpha = gp[G_FLIP]
    lx = gp[G_LX]
    periodic = gp[G_PERIODIC] != 0.0
    for p in prange(n):
        vx, vy, c00, c01, c10, c11, l00, l01, l10, l11 = gather_point(p, x, gp, gv)
        if flip:
            ox, oy = gather_old(p, x, gp, gv_old)
            nvx = alpha * (v[0, p] + vx - ox) + (1.0 - alpha) * vx
            nvy = alpha * (v[1, p] + vy - oy) + (1.0 - alpha) * vy
            # MUSL: the strain rate comes from the remapped momenta (second pass, see advance)
            v[0, p] = nvx
            v[1, p] = nvy
        else:
            if aflip:
                ox, oy = gather_old(p, x, gp, gv_old)
                v[0, p] = alpha * (v[0, p] + vx - ox) + (1.0 - alpha) * vx
                v[1, p] = alpha * (v[1, p] + vy - oy) + (1.0 - alpha) * vy
            else:
                v[0, p] = vx
                v[1, p] = vy
            C[0, p] = c00
            C[1, p] = c01
            C[2, p] = c10
            C[3, p] = c11
        xn = x[0, p] + dt * vx
        yn = x[1, p] + dt * vy
        if periodic:
            if xn >= lx:
                xn -= lx
            elif xn < 0.0:
                xn += lx
        x[0, p] = xn
        x[1, p] = yn
        if not flip:
            _stress(p, l00, l01, l10, l11, dt, v, J, eps, sig, phi, diag, s_int, g_int, mp)
        flags[p] = ST_OK if _inside(gp, xn, yn) else ST_LEFT_GRID


@njit(cache=True, parallel=True)
def update_stress_musl(x, v, J, eps, sig, phi, diag, s_int, g_int, gp, mp, gv, dt, x_old):
    """MUSL stress update from the remapped nodal velocities, evaluated at the old positions."""
    n = x.shape[1]
    for p in prange(n):
        _, _, _, _, _, _, l00, l01, l10, l11 = gather_point(p, x_old, gp, gv)
        _stress(p, l00, l01, l10, l11, dt, v, J, eps, sig, phi, diag, s_int, g_int, mp)


@njit(cache=True, inline="always")
def _stress(p, l00, l01, l10, l11, dt, v, J, eps, sig, phi, diag, s_int, g_int, mp):
    Jn = J[p] * ((1.0 + dt * l00) * (1.0 + dt * l11) - dt * dt * l01 * l10)
    J[p] = Jn
    r = material_update(
        mp, l00, l01, l10, l11, dt, eps[0, p], eps[1, p], eps[2, p], eps[3, p], Jn, phi[p]
    )
    eps[0, p] = r[0]
    eps[1, p] = r[1]
    eps[2, p] = r[2]
    eps[3, p] = r[3]
    sig[0, p] = r[4]
    sig[1, p] = r[5]
    sig[2, p] = r[6]
    sig[3, p] = r[7]
    diag[0, p] = r[8]
    diag[1, p] = r[9]
    diag[2, p] = r[10]
    diag[3, p] = r[11]
    vx = v[0, p]
    vy = v[1, p]
    diag[4, p] = r[12] + math.sqrt(vx * vx + vy * vy)
    diag[5, p] = r[13]
    s_int[p] += r[11] * dt
    g_int[p] += r[9] * dt


@njit(cache=True)
def prime(J, eps, sig, phi, diag, mp, v):
    """Stress, diagnostics and wave speeds of the initial state (no deformation, Δt = 0)."""
    n = J.shape[0]
    s = np.zeros(n)
    g = np.zeros(n)
    for p in range(n):
        _stress(p, 0.0, 0.0, 0.0, 0.0, 0.0, v, J, eps, sig, phi, diag, s, g, mp)


@njit(cache=True)
def _check(x, v, J, sig, diag, flags):
    """Reduce the per-point flags and speeds; returns (status, index, smax, numax)."""
    n = J.shape[0]
    smax = 0.0
    numax = 0.0
    for p in range(n):
        f = flags[p]
        finite = (
            math.isfinite(x[0, p])
            and math.isfinite(x[1, p])
            and math.isfinite(diag[4, p])
            and math.isfinite(sig[0, p] + sig[1, p] + sig[2, p] + sig[3, p])
            and J[p] > 0.0
        )
        if not finite:
            return ST_NONFINITE, p, smax, numax
        if f != ST_OK:
            return f, p, smax, numax
        if diag[4, p] > smax:
            smax = diag[4, p]
        if diag[5, p] > numax:
            numax = diag[5, p]
    return ST_OK, -1, smax, numax


@njit(cache=True)
def advance(
    x, v, C, mass, vol0, J, eps, sig, phi, diag, s_int, g_int,
    gp, mp, sc, grid, gv, gv_old, strip_start, cursor, order, flags, x_old,
    seg_prm, cg, seg_work, t_stop, max_steps,
):  # fmt: skip
    """Advance the state to ``t_stop`` (exactly) or by ``max_steps`` steps, whichever comes first.

    Every time the accumulated time reaches the segregation subcycle (``seg_prm[P_DT_TARGET]``),
    one concentration step (seed Fig. 1 i–k) runs on the extra grid with the time-averaged driver.

    ``sc`` holds the scalar state (time, step counter, last Δt, …; see mpm.params ``S_*``).
    Returns (status, point index, steps taken); status ST_OK or the reason the loop stopped.
    """
    h = gp[G_H]
    cfl = gp[G_CFL]
    flip = gp[G_TRANSFER] == TRANSFER_FLIP
    steps = 0
    while steps < max_steps and sc[S_TIME] < t_stop:
        t = sc[S_TIME]
        dt = gp[G_DTMAX]
        if sc[S_SMAX] > 0.0:
            dt = min(dt, cfl * h / sc[S_SMAX])
        if sc[S_NUMAX] > 0.0:
            dt = min(dt, cfl * h * h / (2.0 * sc[S_NUMAX]))
        if dt < gp[G_DTMIN]:
            return ST_DT_COLLAPSE, -1, steps
        if t + dt * 1.000001 >= t_stop:
            dt = t_stop - t
        ramp = 1.0
        if gp[G_RAMP] > 0.0:
            ramp = min(1.0, (t + dt) / gp[G_RAMP])

        sort_into_strips(x[1], gp, strip_start, cursor, order)
        pres = diag[0]
        p2g(x, v, C, mass, vol0, J, sig, pres, gp, grid, strip_start, order, True)
        grid_update(gp, grid, gv, gv_old, dt, ramp, True)
        if flip:
            x_old[:, :] = x
        update_points(x, v, C, J, eps, sig, phi, diag, s_int, g_int, gp, mp, gv, gv_old, dt, flags)
        if flip:
            # MUSL: remap the updated point momenta (old positions), then the strain rate
            p2g(x_old, v, C, mass, vol0, J, sig, pres, gp, grid, strip_start, order, False)
            momentum_to_velocity(gp, grid, gv)
            update_stress_musl(x, v, J, eps, sig, phi, diag, s_int, g_int, gp, mp, gv, dt, x_old)

        sc[S_TIME] = t + dt
        sc[S_STEP] += 1.0
        sc[S_DT] = dt
        sc[S_TSEG] += dt
        steps += 1
        status, idx, smax, numax = _check(x, v, J, sig, diag, flags)
        sc[S_SMAX] = smax
        sc[S_NUMAX] = numax
        if status != ST_OK:
            return status, idx, steps
        if sc[S_TSEG] >= seg_prm[P_DT_TARGET] * (1.0 - 1e-12):
            if seg_prm[P_MODEL] != 0.0:
                concentration_step(x[0], x[1], vol0, phi, s_int, g_int, sc[S_TSEG], cg, seg_prm,
                                   seg_work)  # fmt: skip
                sc[S_NSEG] += 1.0
            else:
                s_int[:] = 0.0
                g_int[:] = 0.0
            sc[S_TSEG] = 0.0
    return ST_OK, -1, steps


__all__ = ["advance", "prime", "prange"]
