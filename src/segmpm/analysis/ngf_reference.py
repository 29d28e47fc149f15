"""Reference solutions of the nonlocal granular fluidity (NGF) model, independent of the MPM:
a steady 1-D boundary-value solve (scipy) of a uniform chute layer with the sidewall body force,
the h_stop of the linearised model, and the creep length ξ (docs/model.md, "Nonlocal rheology").

Steady, x-uniform layer of depth H, depth ζ = H − y from the free surface. Statics give
p = f ρ_s g cos θ ζ and, with the Coulomb sidewall force fully mobilised wherever the material
moves (the nonlocal model creeps everywhere it is not static), the stress ratio
μ(ζ) = tan θ − β ζ with β = μ_w K_w / W. The steady fluidity solves

    A² d̄² g'' = (μ_s − μ) g + b μ √(ρ_s d̄²/p̃) g²,   g'(0) = 0 (free surface), g(H) = 0 (rough base),

with p̃ = max(p, p_min) (the model's floor, ``material.fluidity_floor_layers``),

and the velocity follows from γ̇ = g μ with u(H) = 0. This requires μ > 0 over the layer, that is
H < tan θ / β (checked).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..config import Config


@dataclass
class NGFParameters:
    """The parameters of a steady NGF chute (SI units)."""

    slope_deg: float
    depth: float
    mu_s: float
    b: float
    A: float
    dbar: float
    rho_s: float = 2650.0
    solid_fraction: float = 0.6
    gravity: float = 9.81
    beta: float = 0.0  #: μ_w K_w / W, 1/m (0: no sidewalls)
    p_min: float = 0.0  #: floor of p in the g² term, Pa
    #: optional (ζ, d̄(ζ)) of a segregated layer: d̄ interpolated on the nodes instead of ``dbar``
    dbar_profile: tuple[np.ndarray, np.ndarray] | None = None

    @classmethod
    def from_config(cls, cfg: Config) -> NGFParameters:
        """The parameters of a configuration's chute (d̄ of the initial mixture)."""
        m, mix, b = cfg.material, cfg.mixture, cfg.boundary
        dbar = mix.phi_small_initial * mix.d_small + (1 - mix.phi_small_initial) * mix.d_large
        beta = b.sidewall_friction * b.wall_normal_stress_ratio / cfg.geometry.width
        from ..materials.params import fluidity_pressure_floor

        return cls(cfg.geometry.slope_deg, cfg.geometry.depth, m.static_friction,
                   m.rate_sensitivity, m.nonlocal_amplitude, dbar, m.grain_density,
                   m.solid_fraction, cfg.time.gravity, beta,
                   fluidity_pressure_floor(cfg))  # fmt: skip


def h_stop(mu_s: float, A: float, dbar: float, slope_deg: float) -> float:
    """Thickness below which a layer without sidewalls cannot flow in the linearised NGF model with
    g = 0 at the base and ∂g/∂ζ = 0 at the surface: the fundamental mode cos(π ζ / 2H) grows iff
    tan θ − μ_s > (A d̄ π / 2H)², so H_stop = (π/2) A d̄ / √(tan θ − μ_s) (∞ if tan θ ≤ μ_s)."""
    ex = math.tan(math.radians(slope_deg)) - mu_s
    return math.inf if ex <= 0 else 0.5 * math.pi * A * dbar / math.sqrt(ex)


def creep_length(mu_s: float, A: float, dbar: float, mu: float) -> float:
    """ξ = A d̄ / √(μ_s − μ): the decay length of g (and of the velocity) where μ < μ_s."""
    return math.inf if mu >= mu_s else A * dbar / math.sqrt(mu_s - mu)


def steady_chute(prm: NGFParameters, n: int = 4000) -> dict[str, np.ndarray]:
    """The steady NGF layer: arrays ``zeta`` (depth), ``y`` (height above the base), ``g``,
    ``mu``, ``p``, ``gdot`` and ``u`` (u(y), 0 at the base).

    Second-order finite differences on ``n`` nodes (ζ_i = (i + ½) Δζ, a mirror node above the
    surface for ∂g/∂ζ = 0, g = 0 on the base ζ = H), solved by pseudo-transient continuation of the
    dynamic equation (implicit Euler with growing steps, Newton in each, banded solves) from the
    local solution: that lands on the flowing branch, not on the trivial g = 0. Converged when the
    residual is below 1e-9 of its scale."""
    from scipy.linalg import solve_banded

    th = math.radians(prm.slope_deg)
    H = prm.depth
    if prm.beta > 0 and H >= math.tan(th) / prm.beta:
        raise ValueError(
            f"depth {H} m reaches μ = 0 at {math.tan(th) / prm.beta:.4g} m: the fully mobilised "
            "sidewall friction would reverse the stress there; use a shallower layer"
        )
    rho = prm.solid_fraction * prm.rho_s
    gc = rho * prm.gravity * math.cos(th)
    dz = H / n
    z = (np.arange(n) + 0.5) * dz
    if prm.dbar_profile is not None:
        zp, dp = (np.asarray(a, dtype=float) for a in prm.dbar_profile)
        o = np.argsort(zp)
        d = np.interp(z, zp[o], dp[o])
    else:
        d = np.full(n, float(prm.dbar))
    mu = math.tan(th) - prm.beta * z
    p = gc * z
    lam = mu - prm.mu_s
    # b μ √(ρ_s d̄²/p) with 1/√ζ averaged over each node's cell (it is singular at the surface,
    # and a point value would converge as Δζ^½ only)
    inv_sqrt = 2.0 * (np.sqrt(z + 0.5 * dz) - np.sqrt(z - 0.5 * dz)) / dz
    if prm.p_min > 0:
        zm = prm.p_min / gc  # the depth of the floor: 1/√p̃ is 1/√p_min above it
        lo, hi = np.maximum(z - 0.5 * dz, 0.0), z + 0.5 * dz
        flat = np.clip(np.minimum(hi, zm) - lo, 0.0, None)
        a = np.maximum(lo, zm)
        curved = np.where(hi > a, 2.0 * (np.sqrt(hi) - np.sqrt(np.minimum(a, hi))), 0.0)
        inv_sqrt = (flat / math.sqrt(zm) + curved) / dz
    c2 = prm.b * mu * d * np.sqrt(prm.rho_s / gc) * inv_sqrt
    D = (prm.A * d) ** 2 / dz**2  # per node (d̄ may vary); the face value is the mean
    gl = np.where(lam > 0, lam / c2, 0.0)
    g = np.maximum(gl, 1e-3 * max(gl.max(), 1.0))

    Df = 0.5 * (D[1:] + D[:-1])  # face coefficients between nodes i and i+1

    def residual(g):
        flux = Df * (g[1:] - g[:-1])
        lap = np.zeros_like(g)
        lap[:-1] += flux
        lap[1:] -= flux
        # the base ζ = H lies half a node below the last node: g(H) = 0 by g_n = −g_{n−1}
        lap[-1] += D[-1] * (-2 * g[-1])
        # the surface: mirror g_{-1} = g_0, no flux
        return lap + lam * g - c2 * g * g

    scale = max(float(np.abs(lam * gl).max()), 1e-30)
    dtau = 1e-3 / max(float(np.abs(lam).max()), 1e-12)
    for _ in range(400):
        g_old = g.copy()
        for _ in range(30):
            r = (g - g_old) / dtau - residual(g)
            # Jacobian of r: 1/dτ − (D L + diag(λ − 2 c₂ g))
            diag = 1 / dtau - lam + 2 * c2 * g
            diag[:-1] += Df
            diag[1:] += Df
            diag[-1] += 2 * D[-1]
            ab = np.zeros((3, n))
            ab[0, 1:] = -Df
            ab[1] = diag
            ab[2, :-1] = -Df
            dg = solve_banded((1, 1), ab, -r)
            g = np.maximum(g + dg, 0.0)
            if np.max(np.abs(dg)) <= 1e-13 * max(float(g.max()), 1e-30):
                break
        res = float(np.max(np.abs(residual(g))))
        if res <= 1e-9 * scale and np.max(np.abs(g - g_old)) <= 1e-11 * max(g.max(), 1e-30):
            break
        dtau *= 2.0
    else:
        raise RuntimeError("steady NGF solve did not converge")
    gdot = g * mu
    # u(ζ) = ∫_ζ^H γ̇ dζ' (midpoint rule on the nodes, u = 0 at the base)
    u = np.cumsum((gdot * dz)[::-1])[::-1] - 0.5 * gdot * dz
    return {"zeta": z, "y": H - z, "g": g, "mu": mu, "p": p, "gdot": gdot, "u": u}
