"""Depth profiles binned normal to the base (``profiles.nc``; README, "Outputs").

Each material point contributes to the bin that holds its centre. Averages are weighted by the
points' reference (solid) volume, except velocity (mass-weighted; equal here because the grain
density is uniform). ``solid_fraction`` is the solid volume in the bin over the bin volume
(L_x × bin thickness, per metre of depth). Empty bins are NaN.
"""

from __future__ import annotations

import numpy as np

from ..state import D_DRIVER, D_INERTIAL, D_PRESSURE, D_SHEAR_RATE, State

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


def point_fluidity(st: State, nonlocal_: bool) -> tuple[np.ndarray, np.ndarray]:
    """(μ, g) of every point: the stress ratio and the fluidity (the state g of the nonlocal
    rheology, else γ̇/μ, the measure a DEM gives)."""
    from ..materials.ngf import stress_ratio_np

    mu = stress_ratio_np(st.sig, st.diag[D_PRESSURE])
    if nonlocal_:
        return mu, st.gf.copy()
    with np.errstate(invalid="ignore", divide="ignore"):
        g = np.where(mu > 0, st.diag[D_SHEAR_RATE] / np.where(mu > 0, mu, 1.0), 0.0)
    return mu, g


def depth_profiles(st: State, edges: np.ndarray, solid_density: float, grain_density: float,
                   length: float | None, nonlocal_: bool = False) -> dict[str, np.ndarray]:  # fmt: skip
    """Profiles on the bins ``edges`` of a state; ``length`` is L_x for the solid fraction;
    ``nonlocal_``: the run has the nonlocal rheology (``fluidity`` is then its state g)."""
    y = st.x[1]
    nb = len(edges) - 1
    idx = np.searchsorted(edges, y, side="right") - 1
    ok = (idx >= 0) & (idx < nb)
    idx = idx[ok]
    wv = st.vol0[ok]
    wm = st.mass[ok]

    def avg(values: np.ndarray, weights: np.ndarray) -> np.ndarray:
        num = np.bincount(idx, weights=weights * values[ok], minlength=nb)
        den = np.bincount(idx, weights=weights, minlength=nb)
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)

    out = {
        "phi_small": avg(st.phi, wv),
        "velocity_x": avg(st.v[0], wm),
        "velocity_y": avg(st.v[1], wm),
        "pressure": avg(st.diag[D_PRESSURE], wv),
        "inertial_number": avg(st.diag[D_INERTIAL], wv),
        "shear_rate": avg(st.diag[D_SHEAR_RATE], wv),
        "segregation_driver": avg(st.diag[D_DRIVER], wv),
        "shear_stress": avg(st.sig[2], wv),
        "normal_stress": avg(-st.sig[1], wv),
    }
    mu, g = point_fluidity(st, nonlocal_)
    out["stress_ratio"] = avg(mu, wv)
    out["fluidity"] = avg(g, wv)
    solid = np.bincount(idx, weights=wm / grain_density, minlength=nb)
    if length is not None and length > 0:
        f = solid / (length * np.diff(edges))
        out["solid_fraction"] = np.where(solid > 0, f, np.nan)
    else:
        out["solid_fraction"] = np.full(nb, np.nan)
    return out
