"""Closed-form steady chute flows of the model (docs/model.md), from a configuration.

The local law gives μ_eff = q_c + a I (b = 1) with the quasi-static friction
q_c = q_φ · 2 r_c/(1 + r_c²) of the yield cap (docs/model.md) and the inertial number
I = γ̇ d̄ / √(p/ρ_s) built on d̄ = φ_s d_s + (1 − φ_s) d_l. With p = f ρ_s g cos θ (H − y):

* Bagnold (no sidewalls): u(y) = (2 I_θ/(3 d̄)) √(f g cos θ) (H^{3/2} − (H − y)^{3/2}),
  I_θ = (tan θ − q_c)/a.
* Sidewall friction μ_w over a width W (Jop et al. 2005): a flowing layer of depth
  ζ_f = W (tan θ − q_c)/μ_w over a static bed; with z = H − y,
  u = √(f g cos θ)/(a d̄) [(2/3) α (ζ_f^{3/2} − z^{3/2}) − (2/5) β (ζ_f^{5/2} − z^{5/2})] for z < ζ_f,
  α = tan θ − q_c, β = μ_w K_w/W.

The nonlocal rheology's local limit (nonlocal amplitude A → 0, t₀ → 0) is the same law with μ_s
for q_c and its b for a: these closed forms then hold for it too (``local_law``).
"""

from __future__ import annotations

import math

import numpy as np

from ..config import Config


def quasi_static_friction(cfg: Config) -> float:
    """q_c = q_φ · 2 r_c/(1 + r_c²): the friction of the yield cap (μ_eff at I → 0)."""
    rc = cfg.material.cap_ratio
    return cfg.material.q_phi * 2.0 * rc / (1.0 + rc * rc)


def local_law(cfg: Config) -> tuple[float, float]:
    """(μ₀, a) of the linear local law μ = μ₀ + a I: (q_c, a) of the local rheology, (μ_s, b)
    of the nonlocal one (its local limit)."""
    m = cfg.material
    if m.model != "fei2016":
        raise ValueError("closed forms need material.model = 'fei2016'")
    if m.rheology == "nonlocal":
        return m.static_friction, m.rate_sensitivity
    if m.b != 1.0:
        raise ValueError("closed forms of the local rheology need b = 1")
    return quasi_static_friction(cfg), m.a * m.sigma_d_factor


def _common(cfg: Config) -> tuple[float, float, float, float, float]:
    m = cfg.material
    mu0, a = local_law(cfg)
    mix = cfg.mixture
    dbar = mix.phi_small_initial * mix.d_small + (1.0 - mix.phi_small_initial) * mix.d_large
    theta = math.radians(cfg.geometry.slope_deg)
    return theta, dbar, a, math.sqrt(m.solid_fraction * cfg.time.gravity * math.cos(theta)), mu0


def bagnold_velocity(cfg: Config, y: np.ndarray) -> np.ndarray:
    """u(y) of the Bagnold layer of depth ``geometry.depth`` without sidewall friction."""
    theta, dbar, a, s, mu0 = _common(cfg)
    inert = (math.tan(theta) - mu0) / a
    if inert <= 0:
        return np.zeros_like(np.asarray(y, dtype=float))
    H = cfg.geometry.depth
    z = np.clip(H - np.asarray(y, dtype=float), 0.0, None)
    return 2.0 * inert / (3.0 * dbar) * s * (H**1.5 - z**1.5)


def sidewall_velocity(cfg: Config, y: np.ndarray) -> tuple[np.ndarray, float]:
    """u(y) and the flowing depth ζ_f of the sidewall-confined layer (above)."""
    theta, dbar, a, s, mu0 = _common(cfg)
    al = math.tan(theta) - mu0
    be = cfg.boundary.sidewall_friction * cfg.boundary.wall_normal_stress_ratio / cfg.geometry.width
    H = cfg.geometry.depth
    if al <= 0:
        return np.zeros_like(np.asarray(y, dtype=float)), 0.0
    zf = min(al / be, H) if be > 0 else H
    z = np.minimum(np.clip(H - np.asarray(y, dtype=float), 0.0, None), zf)
    k = s / (a * dbar)
    return k * ((2 / 3) * al * (zf**1.5 - z**1.5) - (2 / 5) * be * (zf**2.5 - z**2.5)), zf
