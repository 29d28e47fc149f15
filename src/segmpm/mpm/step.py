"""The compiled time loop: ``advance`` runs P2G → grid update → G2P → stress update (USL) →
segregation sub-step, until a target time or a step budget, without returning to Python.

Per step (APIC/AFLIP): the strip sort, P2G (two colours), the grid update, and two passes over
the points, G2P with advection (``update_points``) and the material law with the step check
(``update_stress``).

The time step is recomputed every step from the current state (docs/model.md §1, "Wave speed and
time step"):
Δt = min(C_cfl h / max_p(c_p + |v_p|), C_ν h² / (2 max_p ν_p), Δt_max).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .. import _llvm_options  # noqa: F401  (before any kernel of the time loop compiles)
from .._fmath import fsqrt
from ..materials import (
    VAR_ELASTIC,
    VAR_FEI_LINEAR,
    VAR_FEI_POWER,
    VAR_NGF,
    material_update,
    material_update_var,
    material_variant,
)
from ..materials.params import M_FLU_DT
from ..segregation.closures import P_DT_TARGET, P_MODEL
from ..segregation.grid import concentration_step
from .fluidity import fluidity_step
from .params import (
    G_CFL,
    G_CFLOOR,
    G_DTMAX,
    G_DTMIN,
    G_FLIP,
    G_GX,
    G_GY,
    G_H,
    G_LX,
    G_NX,
    G_NY,
    G_PERIODIC,
    G_RAMP,
    G_TRANSFER,
    G_VISC,
    G_X0,
    G_Y0,
    S_DT,
    S_NFLU,
    S_NSEG,
    S_NUMAX,
    S_SMAX,
    S_STEP,
    S_TFLU,
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
    counting_sort,
    fold_images,
    gather,
    grid_update,
    image_pairs,
    mirror_images,
    momentum_to_velocity,
    p2g,
    strip_index,
    strip_of,
)


@njit(cache=True, error_model="numpy", inline="always")
def _advance_J(J, l00, l01, l10, l11, dt):
    """Volume ratio after the step: J det(I + Δt L)."""
    return J * ((1.0 + dt * l00) * (1.0 + dt * l11) - dt * dt * l01 * l10)


@njit(cache=True, error_model="numpy", inline="always")
def _inside(gp, xp, yp, ih):
    """True if the point's 3×3 stencil lies inside the grid (``ih`` = 1/h)."""
    xi = (yp - gp[G_Y0]) * ih
    if not (xi >= 0.5 and xi < gp[G_NY] - 1.5):
        return False
    if gp[G_PERIODIC] == 0.0:
        xi = (xp - gp[G_X0]) * ih
        if not (xi >= 0.5 and xi < gp[G_NX] - 1.5):
            return False
    return True


@njit(cache=True, error_model="numpy", inline="always")
def _g2p_point(p, x, v, C, J, g, dt, flags, lg, ih, x0, y0, nx, ny, periodic, lx, mode, alpha,
               gp):  # fmt: skip
    """G2P, advection, and (APIC/AFLIP) J of one point (see ``update_points``)."""
    px = x[0, p]
    py = x[1, p]
    flip = mode == TRANSFER_FLIP
    vx, vy, c00, c01, c10, c11, l00, l01, l10, l11, ox, oy = gather(
        px, py, g, ih, x0, y0, nx, ny, periodic
    )
    if flip or mode == TRANSFER_AFLIP:
        v[0, p] = alpha * (v[0, p] + vx - ox) + (1.0 - alpha) * vx
        v[1, p] = alpha * (v[1, p] + vy - oy) + (1.0 - alpha) * vy
    else:
        v[0, p] = vx
        v[1, p] = vy
    xn = px + dt * vx
    yn = py + dt * vy
    if periodic:
        if xn >= lx:
            xn -= lx
        elif xn < 0.0:
            xn += lx
    x[0, p] = xn
    x[1, p] = yn
    if not flip:
        # MUSL (flip) takes the strain rate from the remapped momenta instead (see advance)
        C[0, p] = c00
        C[1, p] = c01
        C[2, p] = c10
        C[3, p] = c11
        Jn = _advance_J(J[p], l00, l01, l10, l11, dt)
        J[p] = Jn
        lg[0, p] = l00
        lg[1, p] = l01
        lg[2, p] = l10
        lg[3, p] = l11
    # a non-finite position fails the test too (NaN compares false; x is not tested by _inside
    # on a periodic grid): the stress pass then needs no read of x
    flags[p] = ST_OK if (math.isfinite(xn) and _inside(gp, xn, yn, ih)) else ST_LEFT_GRID


@njit(cache=True, error_model="numpy", parallel=True, fastmath={"contract"})
def update_points(x, v, C, J, gp, gv, dt, flags, cursor, nstrips, lg):
    """G2P (APIC, AFLIP, or the FLIP/PIC blend of MUSL), advection and J: the first of the two
    point passes of a step (``update_stress`` is the second).

    ``gv`` (N_x, N_y, 4): the nodal velocities of ``grid_update``. ``flags[p]``: 0 ok or
    ST_LEFT_GRID. ``cursor[p]`` receives the P2G strip of the new position (for the next step's
    sort). ``lg`` (4, N) receives the velocity gradient L (00, 01, 10, 11) for the stress pass
    (not for MUSL). The material law runs as its own loop, vectorised over points
    (``update_stress``); the stencil's indirect loads keep this one scalar.
    """
    n = x.shape[1]
    mode = int(gp[G_TRANSFER])
    alpha = gp[G_FLIP]
    lx = gp[G_LX]
    ih = 1.0 / gp[G_H]
    x0 = gp[G_X0]
    y0 = gp[G_Y0]
    nx = gv.shape[0]
    ny = gv.shape[1]
    g = gv.reshape(gv.size)
    periodic = gp[G_PERIODIC] != 0.0
    for p in prange(n):
        _g2p_point(p, x, v, C, J, g, dt, flags, lg, ih, x0, y0, nx, ny, periodic, lx, mode,
                   alpha, gp)  # fmt: skip
        cursor[p] = strip_of(x[1, p], y0, ih, nstrips)


#: points per block of the material pass (``update_stress``), at most
BLOCK = 512

#: rows of a block's buffer in ``update_stress``: shear rate, I, S, c + |v|, ν, failed (1.0)
B_GDOT, B_I, B_S, B_SPEED, B_NU, B_BAD, B_ROWS = range(7)


@njit(cache=True, error_model="numpy", parallel=True, fastmath={"contract"})
def update_stress(x, v, J, eps, sig, phi, gf, diag, s_int, g_int, mp, dt, flags, lg, full,
                  threads):  # fmt: skip
    """The material update of every point from ``lg`` (L of ``update_points``), the subcycle
    integrals, and the step check fused into the same parallel loop.

    ``diag`` (6, N): pressure, shear rate, inertial number, driver S, c + |v|, ν. Only the
    pressure is needed by the next step (P2G); the other rows are written when ``full`` (the
    last step of a call of ``advance``, so every output sees them) and for a failing point.
    ``flags[p]`` from ``update_points`` (position outside the grid or not finite). Returns
    (status, first failing point, max c + |v|, max ν); the failing point is the first in index
    order (a min-reduction), so the diagnostic does not depend on the thread count.
    ``threads``: the number of threads, which only sets the block size. ``gf``: the fluidity of
    the points (read by the nonlocal variant).

    Blocks of up to ``BLOCK`` points run in parallel. In a block, a loop without reductions or
    calls (``_stress_block``, vectorised: four points per AVX2 instruction) updates the state
    and leaves the per-point diagnostics in a buffer, which a short scalar loop reduces
    (``_reduce_block``). The material variant is a constant in each of the three loops.
    """
    n = x.shape[1]
    var = material_variant(mp)
    # at least two blocks per thread, so that few points (the seed case: 596) still split evenly;
    # the block size changes no result (each point on its own, exact max/min reductions)
    size = max(8, min(BLOCK, 8 * ((n + 16 * threads - 1) // (16 * threads))))
    smax = 0.0
    numax = 0.0
    bad = n
    for blk in prange((n + size - 1) // size):
        lo = blk * size
        m = min(size, n - lo)
        buf = np.empty((B_ROWS, size))
        if var == VAR_FEI_LINEAR:
            _stress_block(VAR_FEI_LINEAR, lo, m, buf, v, J, eps, sig, phi, gf, diag, s_int,
                          g_int, mp, dt, flags, lg)  # fmt: skip
        elif var == VAR_NGF:
            _stress_block(VAR_NGF, lo, m, buf, v, J, eps, sig, phi, gf, diag, s_int, g_int,
                          mp, dt, flags, lg)  # fmt: skip
        elif var == VAR_FEI_POWER:
            _stress_block(VAR_FEI_POWER, lo, m, buf, v, J, eps, sig, phi, gf, diag, s_int,
                          g_int, mp, dt, flags, lg)  # fmt: skip
        else:
            _stress_block(VAR_ELASTIC, lo, m, buf, v, J, eps, sig, phi, gf, diag, s_int, g_int,
                          mp, dt, flags, lg)  # fmt: skip
        bs, bn, bb = _reduce_block(lo, m, n, buf, diag, full)
        smax = max(smax, bs)
        numax = max(numax, bn)
        bad = min(bad, bb)
    return _status(bad, n, x, J, sig, diag, flags), (bad if bad < n else -1), smax, numax


@njit(cache=True, error_model="numpy", inline="always")
def _stress_block(var, lo, m, buf, v, J, eps, sig, phi, gf, diag, s_int, g_int, mp, dt, flags,
                  lg):  # fmt: skip
    """The material update of points lo … lo + m − 1 (variant ``var``, a constant): state and
    pressure stored, the diagnostics and the step check (1.0 if failed) into ``buf``. Unsigned
    indices: Numba then emits no negative-index wrap, and the loop vectorises."""
    base = np.uint64(lo)
    for u in range(np.uint64(m)):
        p = base + u
        Jp = J[p]
        r = material_update_var(var, mp, lg[0, p], lg[1, p], lg[2, p], lg[3, p], dt, eps[0, p],
                                eps[1, p], eps[2, p], eps[3, p], Jp, phi[p], gf[p])  # fmt: skip
        speed = _store_state(p, r, dt, v, eps, sig, diag, s_int, g_int)
        ok = _values_ok(flags[p], speed, r[4] + r[5] + r[6] + r[7], Jp)
        buf[B_GDOT, u] = r[9]
        buf[B_I, u] = r[10]
        buf[B_S, u] = r[11]
        buf[B_SPEED, u] = speed
        buf[B_NU, u] = r[13]
        buf[B_BAD, u] = 0.0 if ok else 1.0


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


@njit(cache=True, error_model="numpy", parallel=True)
def update_stress_musl(x, v, J, eps, sig, phi, gf, diag, s_int, g_int, gp, mp, gv, dt, x_old):
    """MUSL stress update from the remapped nodal velocities, evaluated at the old positions."""
    n = x.shape[1]
    ih = 1.0 / gp[G_H]
    x0 = gp[G_X0]
    y0 = gp[G_Y0]
    nx = gv.shape[0]
    ny = gv.shape[1]
    g = gv.reshape(gv.size)
    periodic = gp[G_PERIODIC] != 0.0
    for p in prange(n):
        r = gather(x_old[0, p], x_old[1, p], g, ih, x0, y0, nx, ny, periodic)
        _stress(p, r[6], r[7], r[8], r[9], dt, v, J, eps, sig, phi, gf, diag, s_int, g_int, mp)


@njit(cache=True, error_model="numpy", inline="always")
def _stress(p, l00, l01, l10, l11, dt, v, J, eps, sig, phi, gf, diag, s_int, g_int, mp):
    Jn = _advance_J(J[p], l00, l01, l10, l11, dt)
    J[p] = Jn
    r = material_update(
        mp, l00, l01, l10, l11, dt, eps[0, p], eps[1, p], eps[2, p], eps[3, p], Jn, phi[p], gf[p]
    )
    _store(p, r, dt, v, eps, sig, diag, s_int, g_int)


@njit(cache=True, error_model="numpy", inline="always")
def _store(p, r, dt, v, eps, sig, diag, s_int, g_int):
    """Write the material update ``r`` of point p (contract of ``fei_update``), diagnostics
    included."""
    _store_diag(p, r, _store_state(p, r, dt, v, eps, sig, diag, s_int, g_int), diag)


@njit(cache=True, error_model="numpy", inline="always")
def _store_state(p, r, dt, v, eps, sig, diag, s_int, g_int):
    """Write what the next step needs of the material update ``r`` of point p: strain, stress,
    pressure (``diag[0]``), the subcycle integrals. Returns the signal speed c + |v|."""
    eps[0, p] = r[0]
    eps[1, p] = r[1]
    eps[2, p] = r[2]
    eps[3, p] = r[3]
    sig[0, p] = r[4]
    sig[1, p] = r[5]
    sig[2, p] = r[6]
    sig[3, p] = r[7]
    diag[0, p] = r[8]
    s_int[p] += r[11] * dt
    g_int[p] += r[9] * dt
    vx = v[0, p]
    vy = v[1, p]
    return r[12] + fsqrt(vx * vx + vy * vy)


@njit(cache=True, error_model="numpy", inline="always")
def _store_diag(p, r, speed, diag):
    """The output diagnostics of point p: shear rate, I, S, c + |v|, ν (``diag`` rows 1–5)."""
    diag[1, p] = r[9]
    diag[2, p] = r[10]
    diag[3, p] = r[11]
    diag[4, p] = speed
    diag[5, p] = r[13]


@njit(cache=True, error_model="numpy")
def prime(J, eps, sig, phi, gf, diag, mp, v):
    """Stress, diagnostics and wave speeds of the initial state (no deformation, Δt = 0)."""
    n = J.shape[0]
    s = np.zeros(n)
    g = np.zeros(n)
    for p in range(n):
        _stress(p, 0.0, 0.0, 0.0, 0.0, 0.0, v, J, eps, sig, phi, gf, diag, s, g, mp)


@njit(cache=True, error_model="numpy", inline="always")
def _finite(p, x, J, sig, diag):
    return (
        math.isfinite(x[0, p])
        and math.isfinite(x[1, p])
        and math.isfinite(diag[4, p])
        and math.isfinite(sig[0, p] + sig[1, p] + sig[2, p] + sig[3, p])
        and J[p] > 0.0
    )


@njit(cache=True, error_model="numpy", inline="always")
def _values_ok(flag, speed, sig_sum, J):
    """The step check of one point: its G2P flag (inside the grid, finite position), a finite
    signal speed c + |v| and stress (sum of the components), J > 0."""
    return flag == ST_OK and math.isfinite(speed) and math.isfinite(sig_sum) and J > 0.0


@njit(cache=True, error_model="numpy")
def _status(bad, n, x, J, sig, diag, flags):
    """Status of the first failing point ``bad`` (n: none)."""
    if bad >= n:
        return ST_OK
    return ST_NONFINITE if not _finite(bad, x, J, sig, diag) else flags[bad]


@njit(cache=True, error_model="numpy", parallel=True)
def _check(x, v, J, sig, diag, flags):
    """Reduce the per-point flags and speeds; returns (status, index, smax, numax).

    The index is the first failing point in index order (a min-reduction), so the diagnostic does
    not depend on the thread count. (The APIC/AFLIP path does this inside ``update_stress``.)"""
    n = J.shape[0]
    smax = 0.0
    numax = 0.0
    bad = n
    for p in prange(n):
        if not _values_ok(
            flags[p], diag[4, p], sig[0, p] + sig[1, p] + sig[2, p] + sig[3, p], J[p]
        ):
            bad = min(bad, p)
        smax = max(smax, diag[4, p])
        numax = max(numax, diag[5, p])
    return _status(bad, n, x, J, sig, diag, flags), (bad if bad < n else -1), smax, numax


@njit(cache=True, error_model="numpy")
def advance(
    x, v, C, mass, vol0, J, eps, sig, phi, gf, diag, s_int, g_int,
    gp, mp, sc, grid, gv, strip_start, cursor, order, bounds, flags, x_old, lg, fw,
    seg_prm, cg, seg_work, t_stop, max_steps,
):  # fmt: skip
    """Advance the state to ``t_stop`` (exactly) or by ``max_steps`` steps, whichever comes first.

    Every time the accumulated time reaches the segregation subcycle (``seg_prm[P_DT_TARGET]``),
    one concentration step (seed Fig. 1 i–k) runs on the extra grid with the time-averaged driver.
    With the nonlocal rheology, every ``mp[M_FLU_DT]`` of accumulated time the fluidity ``gf`` is
    advanced (``mpm.fluidity.fluidity_step``: nonlocal diffusion on the grid, local relaxation
    at the points; work array ``fw``).

    ``sc`` holds the scalar state (time, step counter, last Δt, …; see mpm.params ``S_*``).
    Returns (status, point index, steps taken); status ST_OK or the reason the loop stopped.
    The output diagnostics (``diag`` rows 1–5) are written on the last step of the call only
    (``update_stress``), so on return with ST_OK they are that step's; after a failure, the
    failing point's are.
    """
    h = gp[G_H]
    cfl = gp[G_CFL]
    flip = gp[G_TRANSFER] == TRANSFER_FLIP
    nstrips = strip_start.shape[0] - 1
    images = image_pairs(gp, grid.shape[0], grid.shape[1])
    nonlocal_on = material_variant(mp) == VAR_NGF
    steps = 0
    while steps < max_steps and sc[S_TIME] < t_stop:
        t = sc[S_TIME]
        dt = gp[G_DTMAX]
        # the floor keeps Δt at the loaded material's wave speed while (part of) it is a
        # stress-free gas, whose c is 0: otherwise Δt grows during a free flight and the
        # re-contact, stiff at once, is integrated with a step far above its stability limit
        smax = max(sc[S_SMAX], gp[G_CFLOOR])
        if smax > 0.0:
            dt = min(dt, cfl * h / smax)
        if sc[S_NUMAX] > 0.0:
            dt = min(dt, gp[G_VISC] * h * h / (2.0 * sc[S_NUMAX]))
        if dt < gp[G_DTMIN]:
            return ST_DT_COLLAPSE, -1, steps
        # the last step of this call writes the output diagnostics of every point
        last = steps + 1 >= max_steps
        if t + dt * 1.000001 >= t_stop:
            dt = t_stop - t
            last = True
        ramp = 1.0
        if gp[G_RAMP] > 0.0:
            ramp = min(1.0, (t + dt) / gp[G_RAMP])

        if steps == 0:
            strip_index(x[1], gp, cursor, nstrips)
        counting_sort(cursor, strip_start, order, bounds.shape[0] - 1)
        pres = diag[0]
        p2g(x, v, C, mass, vol0, J, sig, pres, gp, grid, strip_start, order, bounds, True)
        fold_images(grid, images, gp[G_GX] * ramp, gp[G_GY])
        grid_update(gp, grid, gv, dt, ramp, True)
        mirror_images(gv, images)
        if flip:
            x_old[:, :] = x
        update_points(x, v, C, J, gp, gv, dt, flags, cursor, nstrips, lg)
        if flip:
            # MUSL: remap the updated point momenta (old positions), then the strain rate
            p2g(x_old, v, C, mass, vol0, J, sig, pres, gp, grid, strip_start, order, bounds, False)
            fold_images(grid, images, 0.0, 0.0)
            momentum_to_velocity(gp, grid, gv)
            mirror_images(gv, images)
            update_stress_musl(x, v, J, eps, sig, phi, gf, diag, s_int, g_int, gp, mp, gv, dt,
                               x_old)  # fmt: skip
            status, idx, smax, numax = _check(x, v, J, sig, diag, flags)
        else:
            status, idx, smax, numax = update_stress(
                x, v, J, eps, sig, phi, gf, diag, s_int, g_int, mp, dt, flags, lg, last,
                bounds.shape[0] - 1,
            )  # fmt: skip

        sc[S_TIME] = t + dt
        sc[S_STEP] += 1.0
        sc[S_DT] = dt
        sc[S_TSEG] += dt
        steps += 1
        sc[S_SMAX] = smax
        sc[S_NUMAX] = numax
        if status != ST_OK:
            return status, idx, steps
        if nonlocal_on:
            sc[S_TFLU] += dt
            if sc[S_TFLU] >= mp[M_FLU_DT] * (1.0 - 1e-12):
                fluidity_step(x, mass, phi, sig, diag[0], gf, gp, mp, fw, sc[S_TFLU])
                sc[S_TFLU] = 0.0
                sc[S_NFLU] += 1.0
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
