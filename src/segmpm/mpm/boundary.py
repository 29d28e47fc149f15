"""Grid boundary conditions (docs/model.md §2).

* periodic x: node indices wrap modulo N_x (in the transfers), points wrap modulo L_x;
* base plane y = y_b and walls x = x_lo, x_hi: no-slip, free-slip (may separate), or Coulomb
  friction (Bardenhagen, Brackbill & Sulsky 2000) on the nodes at and beyond the plane;
* sidewall friction of a 2-D chute: the Coulomb body force −(2 μ_w K_w p / W) v/|v|, which can
  stop a node but never reverse it (Jop, Forterre & Pouliquen 2005).
"""

from __future__ import annotations

import math

from numba import njit

from .params import (
    BC_FRICTION,
    BC_NOSLIP,
    BC_OPEN,
    BC_SLIP,
    G_BASE_KIND,
    G_BASE_MU,
    G_BASE_Y,
    G_H,
    G_PERIODIC,
    G_WALL_MU,
    G_XHI,
    G_XHI_KIND,
    G_XLO,
    G_XLO_KIND,
)


@njit(cache=True, error_model="numpy", inline="always")
def _plane(kind, mu, vn, vt):
    """Wall condition in the wall frame: vn > 0 points away from the wall into the material."""
    if kind == BC_NOSLIP:
        return 0.0, 0.0
    if vn >= 0.0:  # separating: free
        return vn, vt
    if kind == BC_SLIP:
        return 0.0, vt
    # Coulomb friction: the tangential impulse is at most μ times the normal one
    dvn = -vn
    at = abs(vt)
    if at <= mu * dvn:
        return 0.0, 0.0
    return 0.0, vt - mu * dvn * (1.0 if vt > 0.0 else -1.0)


@njit(cache=True, error_model="numpy", inline="always")
def apply_bc(gp, xn, yn, vx, vy):
    """Velocity of the node at (xn, yn) after the base and wall conditions."""
    tol = 1e-9 * gp[G_H]
    kind = int(gp[G_BASE_KIND])
    if kind != BC_OPEN and yn <= gp[G_BASE_Y] + tol:
        vy, vx = _plane(kind, gp[G_BASE_MU], vy, vx)
    if gp[G_PERIODIC] == 0.0:
        kind = int(gp[G_XLO_KIND])
        if kind != BC_OPEN and xn <= gp[G_XLO] + tol:
            vx, vy = _plane(kind, gp[G_WALL_MU], vx, vy)
        kind = int(gp[G_XHI_KIND])
        if kind != BC_OPEN and xn >= gp[G_XHI] - tol:
            nvx, vy = _plane(kind, gp[G_WALL_MU], -vx, vy)
            vx = -nvx
    return vx, vy


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


__all__ = ["BC_FRICTION", "BC_SLIP", "apply_bc", "sidewall_drag", "sidewall_friction"]
