"""Quadratic B-spline shape functions (docs/model.md §2; Steffen, Kirby & Berzins 2008).

In grid units ξ = (x − x0)/h, a point touches the three nodes ``base, base+1, base+2`` with
``base = floor(ξ − 0.5)``. The weights are C¹ and sum to one; their gradients sum to zero.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, error_model="numpy", inline="always")
def bspline2_frac(xi: float) -> tuple[int, float, float, float, float, float, float, float]:
    """Base node, weights w0, w1, w2, derivatives per grid unit d0, d1, d2 of the quadratic
    B-spline at ξ, and the offset f = ξ − base ∈ [0.5, 1.5) (node a lies at (a − f) h from the
    point). A flat tuple: Numba's parallel array analysis rejects nested ones."""
    base = int(math.floor(xi - 0.5))
    f = xi - base
    t0 = 1.5 - f
    t1 = f - 1.0
    t2 = f - 0.5
    return base, 0.5 * t0 * t0, 0.75 - t1 * t1, 0.5 * t2 * t2, -t0, -2.0 * t1, t2, f


@njit(cache=True, error_model="numpy", inline="always")
def bspline2(xi: float) -> tuple[int, float, float, float, float, float, float]:
    """Base node and the weights/derivatives (per grid unit) of the quadratic B-spline at ξ."""
    base, w0, w1, w2, d0, d1, d2, _ = bspline2_frac(xi)
    return base, w0, w1, w2, d0, d1, d2


def bspline2_np(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """NumPy reference: base (n,), weights (n, 3), derivatives per grid unit (n, 3)."""
    xi = np.asarray(xi, dtype=np.float64)
    base = np.floor(xi - 0.5).astype(np.int64)
    f = xi - base
    w = np.stack([0.5 * (1.5 - f) ** 2, 0.75 - (f - 1.0) ** 2, 0.5 * (f - 0.5) ** 2], axis=-1)
    d = np.stack([f - 1.5, -2.0 * (f - 1.0), f - 0.5], axis=-1)
    return base, w, d
