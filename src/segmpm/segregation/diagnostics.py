"""Segregation diagnostics on the material points (NumPy; used between output chunks).

All weights are the constant reference volumes V⁰_p (so the measures are invariant under the
Lagrangian motion and conserved quantities stay conserved).
"""

from __future__ import annotations

import numpy as np


def small_grain_volume(vol0: np.ndarray, phi: np.ndarray) -> float:
    """Total small-grain volume Σ_p V⁰_p φ^s_p (m² per metre of depth in 2-D); an invariant."""
    return float(np.dot(np.asarray(vol0, dtype=np.float64), np.asarray(phi, dtype=np.float64)))


def species_centroids(py: np.ndarray, vol0: np.ndarray, phi: np.ndarray) -> tuple[float, float]:
    """Volume-weighted mean heights (ȳ_s, ȳ_l) of the small and the large grains, m.

    ȳ_s = Σ V⁰ φ y / Σ V⁰ φ and ȳ_l = Σ V⁰ (1−φ) y / Σ V⁰ (1−φ); NaN when a species is absent.
    """
    y = np.asarray(py, dtype=np.float64)
    v = np.asarray(vol0, dtype=np.float64)
    f = np.asarray(phi, dtype=np.float64)
    vs = v * f
    vl = v * (1.0 - f)
    ms, ml = vs.sum(), vl.sum()
    ys = float(np.dot(vs, y) / ms) if ms > 0.0 else float("nan")
    yl = float(np.dot(vl, y) / ml) if ml > 0.0 else float("nan")
    return ys, yl


def segregation_index(
    py: np.ndarray, vol0: np.ndarray, phi: np.ndarray, depth: float | None = None
) -> float:
    """Segregation index SI = 2 (ȳ_l − ȳ_s) / H.

    SI = 0 for a uniform mixture, +1 for a layer completely segregated with the small grains at the
    bottom (normal grading, any φ₀: then ȳ_l − ȳ_s = H/2), −1 for the inverse grading.
    H defaults to the effective thickness 2√3 σ_y of the material (σ_y the volume-weighted standard
    deviation of y), which equals the depth of a uniform layer for any lattice of points.
    """
    ys, yl = species_centroids(py, vol0, phi)
    if depth is None:
        y = np.asarray(py, dtype=np.float64)
        v = np.asarray(vol0, dtype=np.float64)
        ybar = np.dot(v, y) / v.sum()
        depth = 2.0 * np.sqrt(3.0 * np.dot(v, (y - ybar) ** 2) / v.sum())
    if not depth > 0.0:
        return float("nan")
    return float(2.0 * (yl - ys) / depth)
