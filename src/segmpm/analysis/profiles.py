"""The variables and bins of the depth profiles (``profiles.nc``; README, "Outputs"), which
``Simulation.profiles`` computes.

Each material point contributes to the bin that holds its centre. Averages are weighted by the
points' reference (solid) volume, except velocity (mass-weighted; equal here because the grain
density is uniform). ``solid_fraction`` is the solid volume in the bin over the bin volume
(L_x × bin thickness, per metre of depth; × the modelled width in 3-D), each point's solid
volume spread over its slab [y − Δ/2, y + Δ/2] with Δ = h / n_y the points' lattice spacing
along y, so that a lattice whose spacing does not divide the bin does not alias (until
2026-12-08 each point's volume went to the bin of its centre). Empty bins are NaN.
"""

from __future__ import annotations

import numpy as np

PROFILE_VARIABLES = {
    "phi_small": ("1", "small-grain volume fraction of the solid φ_s"),
    "velocity_x": ("m s-1", "downslope velocity u"),
    "velocity_y": ("m s-1", "velocity normal to the base"),
    "pressure": ("Pa", "elastic pressure p_e (mean compressive stress)"),
    "solid_fraction": ("1", "solid volume fraction f"),
    "inertial_number": ("1", "inertial number I = γ̇ d̄ / sqrt(p_e/ρ_s)"),
    "shear_rate": ("s-1", "shear rate γ̇ = sqrt(2 d′:d′)"),
    "segregation_driver": ("Pa", "driving stress S of the segregation flux"),
    "shear_stress": ("Pa", "shear stress σ_xy"),
    "normal_stress": ("Pa", "normal stress −σ_yy (compression positive)"),
    "stress_ratio": ("1", "stress ratio μ = sqrt(½ s:s)/p_e"),
    "fluidity": ("s-1", "granular fluidity g: the nonlocal state g, or γ̇/μ of a local run"),
}

#: scalar time series written beside the profiles (segregation diagnostics, docs/segregation.md)
SCALAR_VARIABLES = {
    "segregation_index": ("1", "SI = 2 (ȳ_l − ȳ_s)/H: 0 mixed, +1 small grains at the bottom"),
    "centroid_small": ("m", "volume-weighted mean height of the small grains ȳ_s"),
    "centroid_large": ("m", "volume-weighted mean height of the large grains ȳ_l"),
    "small_volume_drift": ("1", "relative drift of the total small-grain volume Σ V⁰ φ_s"),
}


def bin_edges(top: float, width: float) -> np.ndarray:
    """Bin edges from the base (y = 0) up to ``top`` (inclusive), ``width`` thick."""
    n = max(1, int(np.ceil(top / width - 1e-9)))
    return np.arange(n + 1) * width
