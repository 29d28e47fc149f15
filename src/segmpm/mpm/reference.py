"""Plain NumPy reference of one plane-strain MPM step (APIC and AFLIP transfers), for testing
the compiled loop of the engine (segmpm.engine) in 2-D.

Slow and simple: every transfer is a vectorised gather or an ``np.add.at`` scatter, in the
layout of segmpm.state (tensor rows xx, yy, xy, zz; the records ``gp``/``sc`` of
segmpm.mpm.params). It follows the engine's algorithm (P2G → grid update → G2P → USL stress
update), written independently of its kernels, so the two must agree to round-off; the tests
translate the engine's records into this layout (tests/test_mpm_reference.py).
"""

from __future__ import annotations

import numpy as np

from ..engine.shape import bspline2_np
from ..materials import KIND_FEI2016_NGF, material_update_np
from ..materials.params import M_FLU_DT, M_KIND
from .params import (
    BC_FRICTION,
    BC_NOSLIP,
    BC_OPEN,
    BC_SLIP,
    G_BASE_KIND,
    G_BASE_MU,
    G_BASE_Y,
    G_CFL,
    G_CFLOOR,
    G_DTMAX,
    G_FLIP,
    G_GX,
    G_GY,
    G_H,
    G_IMAGES,
    G_LX,
    G_NX,
    G_NY,
    G_PERIODIC,
    G_RAMP,
    G_SIDEWALL,
    G_SW_SLOW,
    G_SW_SPEED,
    G_TRANSFER,
    G_VISC,
    G_WALL_MU,
    G_X0,
    G_XHI,
    G_XHI_KIND,
    G_XLO,
    G_XLO_KIND,
    G_Y0,
    S_DT,
    S_NFLU,
    S_NUMAX,
    S_SMAX,
    S_STEP,
    S_TFLU,
    S_TIME,
    S_TSEG,
    TRANSFER_AFLIP,
    TRANSFER_APIC,
)


def _plane_np(kind, mu, vn, vt):
    vn = vn.copy()
    vt = vt.copy()
    if kind == BC_OPEN:
        return vn, vt
    if kind == BC_NOSLIP:
        return np.zeros_like(vn), np.zeros_like(vt)
    into = vn < 0
    if kind == BC_SLIP:
        vn[into] = 0.0
        return vn, vt
    assert kind == BC_FRICTION
    dvn = np.where(into, -vn, 0.0)
    stick = into & (np.abs(vt) <= mu * dvn)
    slide = into & ~stick
    vt[stick] = 0.0
    vt[slide] -= mu * dvn[slide] * np.sign(vt[slide])
    vn[into] = 0.0
    return vn, vt


def apply_bc_np(gp, xn, yn, vx, vy):
    """The boundary planes of the grid update on arrays of nodes (no-slip, slip, Coulomb friction)."""
    tol = 1e-9 * gp[G_H]
    vx, vy = vx.copy(), vy.copy()
    m = yn <= gp[G_BASE_Y] + tol
    vy[m], vx[m] = _plane_np(int(gp[G_BASE_KIND]), gp[G_BASE_MU], vy[m], vx[m])
    if gp[G_PERIODIC] == 0:
        m = xn <= gp[G_XLO] + tol
        vx[m], vy[m] = _plane_np(int(gp[G_XLO_KIND]), gp[G_WALL_MU], vx[m], vy[m])
        m = xn >= gp[G_XHI] - tol
        nvx, vy[m] = _plane_np(int(gp[G_XHI_KIND]), gp[G_WALL_MU], -vx[m], vy[m])
        vx[m] = -nvx
    return vx, vy


def _stencil(gp, x):
    h = gp[G_H]
    bx, wx, dx = bspline2_np((x[0] - gp[G_X0]) / h)
    by, wy, dy = bspline2_np((x[1] - gp[G_Y0]) / h)
    a = np.arange(3)
    ixu = bx[:, None] + a  # (N, 3)
    iy = by[:, None] + a
    ix = ixu % int(gp[G_NX]) if gp[G_PERIODIC] else ixu
    ddx = ixu * h + gp[G_X0] - x[0][:, None]
    ddy = iy * h + gp[G_Y0] - x[1][:, None]
    IX = np.broadcast_to(ix[:, :, None], (len(bx), 3, 3))
    IY = np.broadcast_to(iy[:, None, :], (len(bx), 3, 3))
    W = wx[:, :, None] * wy[:, None, :]
    GX = (dx / h)[:, :, None] * wy[:, None, :]
    GY = wx[:, :, None] * (dy / h)[:, None, :]
    DX = np.broadcast_to(ddx[:, :, None], W.shape)
    DY = np.broadcast_to(ddy[:, None, :], W.shape)
    return IX, IY, W, GX, GY, DX, DY


def _image_planes_np(gp: np.ndarray, nx: int, ny: int) -> tuple[int, int, int]:
    """Node indices of the no-slip walls with image nodes (−1: none), as mpm.transfer."""

    def plane(coord: float, origin: float, n: int) -> int:
        r = (coord - origin) / gp[G_H]
        k = int(np.floor(r + 0.5))
        return k if abs(r - k) <= 1e-6 and 1 <= k <= n - 2 else -1

    if gp[G_IMAGES] == 0:
        return -1, -1, -1
    jb = plane(gp[G_BASE_Y], gp[G_Y0], ny) if gp[G_BASE_KIND] == BC_NOSLIP else -1
    il = ih = -1
    if not gp[G_PERIODIC]:
        il = plane(gp[G_XLO], gp[G_X0], nx) if gp[G_XLO_KIND] == BC_NOSLIP else -1
        ih = plane(gp[G_XHI], gp[G_X0], nx) if gp[G_XHI_KIND] == BC_NOSLIP else -1
    return jb, il, ih


#: parity of the P2G fields under the odd extension across a no-slip wall (m, mv, f, V p)
_PARITY = np.array([1.0, -1.0, -1.0, -1.0, -1.0, 1.0])


def _fold_np(f: np.ndarray, jb: int, il: int, ih: int, gx: float, gy: float) -> None:
    """Fold the fields (6, nx, ny) of the nodes behind each wall onto their mirrors."""
    nx, ny = f.shape[1], f.shape[2]

    def fold(src, dst):
        g = f[(slice(None), *src)].copy()
        g[3] += 2.0 * g[0] * gx
        g[4] += 2.0 * g[0] * gy
        f[(slice(None), *dst)] += _PARITY[:, None] * g
        f[(slice(None), *src)] = 0.0

    for k in range(1, jb + 1) if jb > 0 else ():
        if jb + k < ny:
            fold((slice(None), jb - k), (slice(None), jb + k))
    for k in range(1, il + 1) if il > 0 else ():
        if il + k < nx:
            fold((il - k, slice(None)), (il + k, slice(None)))
    for k in range(1, nx - ih) if ih > 0 else ():
        if ih - k >= 0:
            fold((ih + k, slice(None)), (ih - k, slice(None)))


def _mirror_np(g: np.ndarray, jb: int, il: int, ih: int) -> None:
    """Nodal values behind each wall: minus their mirrors'."""
    nx, ny = g.shape
    for k in range(1, jb + 1) if jb > 0 else ():
        g[:, jb - k] = -g[:, jb + k if jb + k < ny else jb]
    for k in range(1, il + 1) if il > 0 else ():
        g[il - k, :] = -g[il + k if il + k < nx else il, :]
    for k in range(1, nx - ih) if ih > 0 else ():
        g[ih + k, :] = -g[ih - k if ih - k >= 0 else ih, :]


def step_np(arrays: dict[str, np.ndarray], gp: np.ndarray, mp: np.ndarray) -> dict[str, np.ndarray]:
    """One step of the APIC/USL algorithm on copies of the state arrays; returns the new ones."""
    s = {k: np.array(v, dtype=np.float64, copy=True) for k, v in arrays.items()}
    x, v, C, sig = s["x"], s["v"], s["C"], s["sig"]
    sc = s["sc"]
    h = gp[G_H]
    nx, ny = int(gp[G_NX]), int(gp[G_NY])
    dt = gp[G_DTMAX]
    smax = max(sc[S_SMAX], gp[G_CFLOOR])
    if smax > 0:
        dt = min(dt, gp[G_CFL] * h / smax)
    if sc[S_NUMAX] > 0:
        dt = min(dt, gp[G_VISC] * h * h / (2 * sc[S_NUMAX]))
    t = sc[S_TIME]
    ramp = min(1.0, (t + dt) / gp[G_RAMP]) if gp[G_RAMP] > 0 else 1.0

    IX, IY, W, GX, GY, DX, DY = _stencil(gp, x)
    m = s["mass"][:, None, None]
    vol = (s["vol0"] * s["J"])[:, None, None]
    gm = np.zeros((nx, ny))
    gmx = np.zeros((nx, ny))
    gmy = np.zeros((nx, ny))
    gfx = np.zeros((nx, ny))
    gfy = np.zeros((nx, ny))
    gvp = np.zeros((nx, ny))
    mw = m * W
    np.add.at(gm, (IX, IY), mw)
    c = C[:, :, None, None]
    np.add.at(gmx, (IX, IY), mw * (v[0][:, None, None] + c[0] * DX + c[1] * DY))
    np.add.at(gmy, (IX, IY), mw * (v[1][:, None, None] + c[2] * DX + c[3] * DY))
    sxx, syy, sxy = (sig[k][:, None, None] for k in range(3))
    np.add.at(gfx, (IX, IY), -vol * (sxx * GX + sxy * GY))
    np.add.at(gfy, (IX, IY), -vol * (sxy * GX + syy * GY))
    np.add.at(gvp, (IX, IY), W * vol * s["diag"][0][:, None, None])

    jb, il, ih = _image_planes_np(gp, nx, ny)
    if max(jb, il, ih) > 0:
        fields = np.stack([gm, gmx, gmy, gfx, gfy, gvp])
        _fold_np(fields, jb, il, ih, gp[G_GX] * ramp, gp[G_GY])
        gm, gmx, gmy, gfx, gfy, gvp = fields
    has = gm > 0
    safe = np.where(has, gm, 1.0)
    vox, voy = gmx / safe, gmy / safe
    vx = vox + dt * (gfx / safe + gp[G_GX] * ramp)
    vy = voy + dt * (gfy / safe + gp[G_GY])
    sw = gp[G_SIDEWALL] * ramp
    uw = gp[G_SW_SPEED]
    sw0 = gp[G_SW_SLOW] * ramp if uw > 0 else sw
    if sw > 0 or sw0 > 0:
        # the Coulomb body force 2 μ_w K_w p / W per unit volume, integrated: Σ w V p / m, with
        # μ_w(u) = μ_w0 + (μ_w − μ_w0) u/(u + u_w) when u_w > 0
        act = has & (gvp > 0)
        speed = np.hypot(vx, vy)
        fac = sw0 + (sw - sw0) * speed / (speed + uw) if uw > 0 else sw
        dvmax = np.where(act, dt * fac * gvp / safe, 0.0)
        f = np.where(speed <= dvmax, 0.0, 1.0 - dvmax / np.where(speed > 0, speed, 1.0))
        vx = np.where(act, vx * f, vx)
        vy = np.where(act, vy * f, vy)
    XN, YN = np.meshgrid(gp[G_X0] + np.arange(nx) * h, gp[G_Y0] + np.arange(ny) * h, indexing="ij")
    bx_, by_ = apply_bc_np(gp, XN.ravel(), YN.ravel(), vx.ravel(), vy.ravel())
    gvx = np.where(has, bx_.reshape(nx, ny), 0.0)
    gvy = np.where(has, by_.reshape(nx, ny), 0.0)
    ox_, oy_ = apply_bc_np(gp, XN.ravel(), YN.ravel(), vox.ravel(), voy.ravel())
    gox = np.where(has, ox_.reshape(nx, ny), 0.0)
    goy = np.where(has, oy_.reshape(nx, ny), 0.0)
    for g in (gvx, gvy, gox, goy):
        _mirror_np(g, jb, il, ih)

    ux = gvx[IX, IY]
    uy = gvy[IX, IY]
    vpx = np.sum(W * ux, axis=(1, 2))
    vpy = np.sum(W * uy, axis=(1, 2))
    k = 4.0 / h**2
    C[0] = k * np.sum(W * ux * DX, axis=(1, 2))
    C[1] = k * np.sum(W * ux * DY, axis=(1, 2))
    C[2] = k * np.sum(W * uy * DX, axis=(1, 2))
    C[3] = k * np.sum(W * uy * DY, axis=(1, 2))
    L = np.empty((len(vpx), 2, 2))
    L[:, 0, 0] = np.sum(ux * GX, axis=(1, 2))
    L[:, 0, 1] = np.sum(ux * GY, axis=(1, 2))
    L[:, 1, 0] = np.sum(uy * GX, axis=(1, 2))
    L[:, 1, 1] = np.sum(uy * GY, axis=(1, 2))
    if gp[G_TRANSFER] == TRANSFER_AFLIP:
        a = gp[G_FLIP]
        dvx = vpx - np.sum(W * gox[IX, IY], axis=(1, 2))
        dvy = vpy - np.sum(W * goy[IX, IY], axis=(1, 2))
        v[0], v[1] = a * (v[0] + dvx) + (1 - a) * vpx, a * (v[1] + dvy) + (1 - a) * vpy
    else:
        assert gp[G_TRANSFER] == TRANSFER_APIC, "the reference implements APIC and AFLIP"
        v[0], v[1] = vpx, vpy
    x[0] += dt * vpx
    x[1] += dt * vpy
    if gp[G_PERIODIC]:
        x[0] = np.where(
            x[0] >= gp[G_LX], x[0] - gp[G_LX], np.where(x[0] < 0, x[0] + gp[G_LX], x[0])
        )
    s["J"] = s["J"] * (
        (1 + dt * L[:, 0, 0]) * (1 + dt * L[:, 1, 1]) - dt**2 * L[:, 0, 1] * L[:, 1, 0]
    )
    eps_new, sig_new, p, gdot, inert, S, cw, nu = material_update_np(
        mp, L, dt, s["eps"].T, s["J"], s["phi"], s["gf"]
    )
    s["eps"] = eps_new.T.copy()
    s["sig"] = sig_new.T.copy()
    s["diag"][0], s["diag"][1], s["diag"][2], s["diag"][3] = p, gdot, inert, S
    s["diag"][4] = cw + np.hypot(v[0], v[1])
    s["diag"][5] = nu
    s["s_int"] += S * dt
    s["g_int"] += gdot * dt
    sc[S_TIME] = t + dt
    sc[S_STEP] += 1
    sc[S_DT] = dt
    sc[S_TSEG] += dt
    if mp[M_KIND] == KIND_FEI2016_NGF:
        sc[S_TFLU] += dt
        if sc[S_TFLU] >= mp[M_FLU_DT] * (1.0 - 1e-12):
            from .fluidity import fluidity_step_np

            s["gf"], _ = fluidity_step_np(x, s["mass"], s["phi"], s["sig"], s["diag"][0],
                                          s["gf"], gp, mp, sc[S_TFLU])  # fmt: skip
            sc[S_TFLU] = 0.0
            sc[S_NFLU] += 1
    sc[S_SMAX] = s["diag"][4].max()
    sc[S_NUMAX] = s["diag"][5].max()
    return s
