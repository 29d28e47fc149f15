"""Plain NumPy twin of the compiled concentration step, and closed-form reference solutions.

``concentration_step_ref`` follows exactly the algorithm of :func:`segmpm.segregation.grid.
concentration_step` (same weights, same frozen face coefficients, same substep count), vectorised
over particles and cells with NumPy, so the two can be compared to round-off. It is slow-ish and
allocates; use it for verification only.

The closed forms are those of docs/segregation.md §4 (Gray & Thornton 2005 shocks, the zero-flux
steady state logit φ = G(y) − G₀ with G = ∫ w/D dy, the Boltzmann-like profile for the seed model).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import brentq

from segmpm.segregation.closures import (
    F_UPWIND,
    M_FAN2014,
    M_GRAY_THORNTON,
    M_HILL_TAN_FULL,
    M_HILL_TAN_REDUCED,
    M_LIU_HENANN,
    M_NONE,
    P_B_CS,
    P_B_KS,
    P_C_D,
    P_D_LARGE,
    P_D_SMALL,
    P_DIFF,
    P_ETA,
    P_FAN_D,
    P_FAN_S,
    P_FILL_MIN,
    P_FLUX,
    P_GX,
    P_GY,
    P_LH_CDIFF,
    P_LH_CP,
    P_LH_CSEG,
    P_MODEL,
    P_Q,
    P_Q_SHEAR,
    P_RHO_BULK,
    P_SAFETY,
)
from segmpm.segregation.grid import ConcGrid

# ---- kernel twin -----------------------------------------------------------------------------


def tent_weights_np(
    x: np.ndarray, x0: float, hc: float, n: int, periodic: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Vectorised tent weights (i0, i1, w0, w1) to cell centres x0 + (i + ½) h_c."""
    f = (np.asarray(x, dtype=np.float64) - x0) / hc - 0.5
    f = np.where(np.isnan(f), 0.0, f)
    fi = np.floor(f)
    t = f - fi
    i0 = fi.astype(np.int64)
    if periodic == 1:
        i0 = np.mod(i0, n)
        i1 = np.where(i0 + 1 >= n, 0, i0 + 1)
    else:
        if n < 2:
            z = np.zeros_like(i0)
            return z, z, np.ones_like(t), np.zeros_like(t)
        lo = i0 < 0
        hi = i0 > n - 2
        i0 = np.where(lo, 0, np.where(hi, n - 2, i0))
        t = np.where(lo, 0.0, np.where(hi, 1.0, t))
        i1 = i0 + 1
    return i0, i1, 1.0 - t, t


def face_velocity_diffusivity_np(
    prm: np.ndarray,
    s_a: np.ndarray,
    s_b: np.ndarray,
    g_a: np.ndarray,
    g_b: np.ndarray,
    dbar_a: np.ndarray,
    dbar_b: np.ndarray,
    hc: float,
    normal_y: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised twin of ``closures.face_velocity_diffusivity`` (w, D on faces a → b)."""
    model = int(prm[P_MODEL])
    zero = np.zeros_like(s_a)
    if model == M_HILL_TAN_REDUCED:
        w = -prm[P_B_KS] / (prm[P_C_D] * prm[P_RHO_BULK]) * ((s_b - s_a) / hc)
        return w, zero + prm[P_ETA] / prm[P_C_D]
    if model == M_HILL_TAN_FULL:
        gn = prm[P_GY] if normal_y == 1 else prm[P_GX]
        w = (prm[P_B_CS] - prm[P_B_KS]) / (prm[P_C_D] * prm[P_RHO_BULK]) * ((s_b - s_a) / hc)
        w = w - prm[P_B_CS] / prm[P_C_D] * gn
        return w, zero + prm[P_ETA] / prm[P_C_D]
    if model == M_GRAY_THORNTON:
        if normal_y == 1:
            if prm[P_Q_SHEAR] != 0.0:
                w = -prm[P_Q] * 0.5 * (g_a + g_b) * 0.5 * (dbar_a + dbar_b)
            else:
                w = zero - prm[P_Q]
        else:
            w = zero
        return w, zero + prm[P_DIFF]
    if model == M_LIU_HENANN:
        gdot = 0.5 * (g_a + g_b)
        pf = 0.5 * (s_a + s_b)
        dbar = 0.5 * (dbar_a + dbar_b)
        w = -prm[P_LH_CSEG] * (g_b - g_a) / hc
        with np.errstate(invalid="ignore", divide="ignore"):
            w = w + np.where(
                pf > 0, prm[P_LH_CP] * gdot / np.where(pf > 0, pf, 1) * (s_b - s_a) / hc, 0
            )
        return w * dbar**2, prm[P_LH_CDIFF] * gdot * dbar**2
    if model == M_FAN2014:
        gdot = 0.5 * (g_a + g_b)
        dbar = 0.5 * (dbar_a + dbar_b)
        w = -prm[P_FAN_S] * gdot if normal_y == 1 else zero
        return w, prm[P_FAN_D] * gdot * dbar * dbar
    return zero, zero.copy()


def _bernoulli_np(x: np.ndarray) -> np.ndarray:
    small = np.abs(x) < 1e-10
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        out = x / np.expm1(x)
    return np.where(small, 1.0 - 0.5 * x, out)


def face_rates_np(
    w: np.ndarray, d: np.ndarray, hc: float, flux_kind: int
) -> tuple[np.ndarray, np.ndarray]:
    """Vectorised twin of ``closures.face_rates``: (a, b) of F = a φ_a(1−φ_b) − b φ_b(1−φ_a)."""
    wp = np.maximum(w, 0.0)
    wm = np.maximum(-w, 0.0)
    if flux_kind == F_UPWIND:
        return wp + d / hc, wm + d / hc
    with np.errstate(divide="ignore", invalid="ignore"):
        p = np.where(d > 0.0, w * hc / np.where(d > 0.0, d, 1.0), 0.0)
    upw = (d <= 0.0) | (np.abs(p) > 700.0)
    a = np.where(upw, wp, d / hc * _bernoulli_np(-p))
    b = np.where(upw, wm, d / hc * _bernoulli_np(p))
    return a, b


def concentration_step_ref(
    px: np.ndarray,
    py: np.ndarray,
    vol0: np.ndarray,
    phi: np.ndarray,
    s_int: np.ndarray,
    gdot_int: np.ndarray,
    t_int: float,
    cg: ConcGrid,
    prm: np.ndarray,
) -> int:
    """NumPy twin of ``grid.concentration_step`` (same in-place semantics, returns substeps)."""
    if int(prm[P_MODEL]) == M_NONE or not (t_int > 0.0):
        s_int[:] = 0.0
        gdot_int[:] = 0.0
        return 0
    hc, ncx, ncy, per = cg.hc, cg.ncx, cg.ncy, cg.periodic_x
    ncell = ncx * ncy
    i0, i1, wx0, wx1 = tent_weights_np(px, cg.x0, hc, ncx, per)
    j0, j1, wy0, wy1 = tent_weights_np(py, cg.y0, hc, ncy, 0)
    cells = [i0 * ncy + j0, i0 * ncy + j1, i1 * ncy + j0, i1 * ncy + j1]
    raw = [wx0 * wy0, wx0 * wy1, wx1 * wy0, wx1 * wy1]

    # (i) MP → grid. Pass 1: the raw fill decides activity; pass 2: weights restricted to the
    # active cells and renormalised (``_corners`` of the engine's step).
    vol_raw = np.zeros(ncell)
    for idx, w in zip(cells, [r / (raw[0] + raw[1] + raw[2] + raw[3]) for r in raw], strict=True):
        vol_raw += np.bincount(idx, weights=w * vol0, minlength=ncell)
    act = vol_raw >= prm[P_FILL_MIN] * hc * hc
    masked = [w * act[idx] for idx, w in zip(cells, raw, strict=True)]
    tot = masked[0] + masked[1] + masked[2] + masked[3]
    has = tot > 0.0
    weights = [
        np.where(has, m / np.where(has, tot, 1.0), w) for m, w in zip(masked, raw, strict=True)
    ]
    combos = list(zip(cells, weights, strict=True))
    act = act.reshape(ncx, ncy)

    def scatter(q: np.ndarray) -> np.ndarray:
        out = np.zeros(ncell)
        for idx, w in combos:
            out += np.bincount(idx, weights=w * vol0 * q, minlength=ncell)
        return out.reshape(ncx, ncy)

    one = np.ones_like(phi)
    vol = scatter(one)
    sum_s = scatter(phi)
    sum_l = scatter(1.0 - phi)
    occupied = vol > 0.0
    safe = np.where(occupied, vol, 1.0)
    phic = np.where(occupied, np.clip(sum_s / safe, 0.0, 1.0), 0.0)
    sc = np.where(occupied, scatter(s_int) / (safe * t_int), 0.0)
    gc = np.where(occupied, scatter(gdot_int) / (safe * t_int), 0.0)
    theta = vol / (hc * hc)
    phi0 = phic.copy()

    # (j) frozen face coefficients
    flux_kind = int(prm[P_FLUX])
    dbar = prm[P_D_SMALL] * phic + prm[P_D_LARGE] * (1.0 - phic)
    # x-faces (i, j) | (i+1, j)
    r = lambda q: np.roll(q, -1, axis=0)  # noqa: E731  (neighbour in +x, wrapped)
    w, d = face_velocity_diffusivity_np(prm, sc, r(sc), gc, r(gc), dbar, r(dbar), hc, 0)
    ax, bx = face_rates_np(w, d, hc, flux_kind)
    okx = act & r(act)
    if per != 1:
        okx[-1, :] = False
    if ncx == 1:
        okx[:] = False
    ax = np.where(okx, ax, 0.0)
    bx = np.where(okx, bx, 0.0)
    # y-faces (i, j) | (i, j+1)
    u = lambda q: np.roll(q, -1, axis=1)  # noqa: E731
    w, d = face_velocity_diffusivity_np(prm, sc, u(sc), gc, u(gc), dbar, u(dbar), hc, 1)
    ay, by = face_rates_np(w, d, hc, flux_kind)
    oky = act & u(act)
    oky[:, -1] = False
    ay = np.where(oky, ay, 0.0)
    by = np.where(oky, by, 0.0)

    mx = np.maximum(ax, bx)
    my = np.maximum(ay, by)
    rate = mx + my + np.roll(mx, 1, axis=0) + np.roll(my, 1, axis=1)
    rate = np.where(act, rate / np.where(act, theta * hc, 1.0), 0.0)
    rate_max = float(rate.max()) if rate.size else 0.0
    if not math.isfinite(rate_max):
        nsub = 1
    elif rate_max > 0.0:
        nsub = max(1, math.ceil(t_int * rate_max / prm[P_SAFETY]))
    else:
        nsub = 0
    dt = t_int / nsub if nsub else 0.0
    denom = np.where(theta > 0.0, theta * hc, 1.0)
    for _ in range(nsub):
        pr = r(phic)
        fx = ax * phic * (1.0 - pr) - bx * pr * (1.0 - phic)
        pu = u(phic)
        fy = ay * phic * (1.0 - pu) - by * pu * (1.0 - phic)
        div = fx - np.roll(fx, 1, axis=0) + fy - np.roll(fy, 1, axis=1)
        phic = phic - dt * div / denom

    # (k) grid → MP, incremental and bound-preserving
    if nsub:
        dc = (phic - phi0).ravel()
        vflat, sl, ss = vol.ravel(), sum_l.ravel(), sum_s.ravel()
        dphi = np.zeros_like(phi)
        with np.errstate(divide="ignore", invalid="ignore"):
            for idx, w in combos:
                g = dc[idx]
                up = (g > 0.0) & (sl[idx] > 0.0)
                dn = (g < 0.0) & (ss[idx] > 0.0)
                dphi += np.where(up, w * g * (1.0 - phi) * vflat[idx] / sl[idx], 0.0)
                dphi += np.where(dn, w * g * phi * vflat[idx] / ss[idx], 0.0)
        phi[:] = np.clip(phi + dphi, 0.0, 1.0)
    s_int[:] = 0.0
    gdot_int[:] = 0.0
    return nsub


# ---- synthetic layouts -----------------------------------------------------------------------


def strip_layout(
    length: float,
    depth: float,
    spacing: float,
    *,
    x0: float = 0.0,
    y0: float = 0.0,
    jitter: float = 0.0,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Material points on a regular lattice filling [x0, x0+length] × [y0, y0+depth].

    Points sit at the centres of spacing × spacing squares, vol0 = spacing²; ``jitter`` (a fraction
    of the spacing) displaces them randomly (uniform) to break the lattice.
    """
    nx = round(length / spacing)
    ny = round(depth / spacing)
    xs = x0 + (np.arange(nx) + 0.5) * spacing
    ys = y0 + (np.arange(ny) + 0.5) * spacing
    px, py = (a.ravel().copy() for a in np.meshgrid(xs, ys, indexing="ij"))
    if jitter > 0.0:
        rng = np.random.default_rng(seed)
        px += jitter * spacing * rng.uniform(-0.5, 0.5, px.size)
        py += jitter * spacing * rng.uniform(-0.5, 0.5, py.size)
    return px, py, np.full(px.size, spacing * spacing)


# ---- closed-form references (docs/segregation.md §4) ------------------------------------------


def shock_positions(q: float, phi0: float, depth: float, t: float) -> tuple[float, float]:
    """Gray–Thornton inviscid shocks from a uniform φ₀ with percolation speed q (small sink).

    Returns (y_top_of_pure_small, y_bottom_of_pure_large) = (q φ₀ t, H − q (1 − φ₀) t), valid
    while the two shocks have not met (t < H/q).
    """
    return q * phi0 * t, depth - q * (1.0 - phi0) * t


def steady_logit_profile(g_of_y: np.ndarray, weights: np.ndarray, phi_mean: float) -> np.ndarray:
    """Zero-flux steady state logit φ = G(y) − G₀ (docs/segregation.md §4), at given points.

    ``g_of_y`` holds G(y) = ∫ w/D dy at the points (for the seed model G = −b^{k,s} S/(ρ η)),
    ``weights`` their volumes; G₀ is fixed by Σ weights φ = φ_mean Σ weights (a 1-D root find).
    """
    g = np.asarray(g_of_y, dtype=np.float64)
    wts = np.asarray(weights, dtype=np.float64)
    target = phi_mean * wts.sum()

    def excess(g0: float) -> float:
        return float(np.sum(wts * _sigmoid(g - g0)) - target)

    lo, hi = g.min() - 50.0, g.max() + 50.0
    g0 = brentq(excess, lo, hi, xtol=1e-14, rtol=1e-15, maxiter=500)
    return _sigmoid(g - g0)


def _sigmoid(z: np.ndarray) -> np.ndarray:
    return 0.5 * (1.0 + np.tanh(0.5 * z))


def logistic_width_fit(
    y: np.ndarray, phi: np.ndarray, guess: tuple[float, float]
) -> tuple[float, float]:
    """Least-squares fit φ ≈ 1/(1 + exp((y − y₀)/ℓ)); returns (y₀, ℓ).

    For a Gray–Thornton steady state ℓ = D/q, so q ℓ is an effective diffusivity.
    """
    from scipy.optimize import curve_fit

    def model(yy: np.ndarray, y0: float, ell: float) -> np.ndarray:
        return _sigmoid(-(yy - y0) / ell)

    popt, _ = curve_fit(model, y, phi, p0=guess, maxfev=20000)
    return float(popt[0]), float(abs(popt[1]))
