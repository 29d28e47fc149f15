"""Segregation closures: the face velocity w and diffusivity D of the small-grain flux.

Every closure is written in the common form (docs/segregation.md §1)

    Ψ = w φ(1−φ) − D ∇φ                         (small-grain volume flux per unit solid fraction f)

with φ = φ^s, a face-normal segregation velocity ``w`` (positive along the face normal n) and a
diffusivity ``D``, both evaluated from the two cells that share the face. The closure is chosen by an
integer code stored in the parameter vector ``prm`` (never by a string in compiled code).

Closures (codes ``M_*``):

* ``hill_tan_reduced`` (seed Eq. 6, the default): w = −(b^{k,s}/(c_D ρ)) ∂S/∂n, D = η/c_D.
* ``hill_tan_full`` (seed Eq. 1 in vector form, Hill & Tan 2014, with
  ψ^{c,s} = φ + b^{c,s}φ(1−φ) and ψ^{k,s} = φ + b^{k,s}φ(1−φ)):
  w = ((b^{c,s} − b^{k,s})/(c_D ρ)) ∂S/∂n − (b^{c,s}/c_D) g·n, D = η/c_D.
* ``hill_tan_fluidity``: ``hill_tan_full`` with S = σ^k = κ_g ρ (g d̄)², the kinetic stress of the
  fluctuation speed δv = g d̄/F of the nonlocal fluidity g (Zhang & Kamrin 2017; κ_g = 1/F², the
  engine computes S; nonlocal rheology only).
* ``liu_henann`` (the relative flux of Liu, Singh & Henann 2023, driven by shear-rate gradients,
  with the pressure-gradient term of Singh, Liu & Henann 2024, in the form of docs/segregation.md):
  w = d̄² (−C_seg ∂γ̇/∂n + C_p (γ̇/p) ∂p/∂n), D = C_diff γ̇ d̄². Small grains move toward lower
  shear rate and toward higher pressure; S = p (driver P, time-averaged like γ̇).
* ``gray_thornton`` (Gray & Thornton 2005): w_y = −q (m/s), or w_y = −q γ̇ d̄ with q dimensionless
  when ``q_shear_scaled``; w_x = 0; D = ``diffusivity``.
* ``fan2014`` (Fan, Schlick, Umbanhowar, Ottino & Lueptow 2014, *JFM* 741): w_y = −S_r γ̇ with
  S_r = ``fan_S`` (m) — their w_s = S_r γ̇ (1−φ) is the (1−φ) of the φ(1−φ) form —, w_x = 0,
  D = ``fan_D_coeff`` γ̇ d̄².
* ``none``: no flux.

ρ = f ρ_s is the bulk density, S the driving stress (the proxy of docs/segregation.md §1, already
scaled by κ by the engine), γ̇ the shear rate, d̄ = φ d_s + (1−φ) d_l, g = (g sin θ, −g cos θ) the
gravity vector in the slope frame. Face values of S-gradients are two-point differences; face
values of γ̇ and d̄ are averages of the two cells.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit

# ---- closure codes (prm[P_MODEL]) ------------------------------------------------------------
M_NONE = 0
M_HILL_TAN_REDUCED = 1
M_HILL_TAN_FULL = 2
M_GRAY_THORNTON = 3
M_FAN2014 = 4
M_LIU_HENANN = 5
MODEL_CODES: dict[str, int] = {
    "none": M_NONE,
    "hill_tan_reduced": M_HILL_TAN_REDUCED,
    "hill_tan_full": M_HILL_TAN_FULL,
    # the same flux, with the kinetic stress of the fluidity as S (driver G)
    "hill_tan_fluidity": M_HILL_TAN_FULL,
    "liu_henann": M_LIU_HENANN,
    "gray_thornton": M_GRAY_THORNTON,
    "fan2014": M_FAN2014,
}

# ---- face-flux codes (prm[P_FLUX]) -----------------------------------------------------------
F_SG = 0  #: exponentially fitted Scharfetter–Gummel flux (default)
F_UPWIND = 1  #: upwind segregation + central diffusion (kept as a switch, docs/segregation.md §2)
FLUX_CODES: dict[str, int] = {"sg": F_SG, "upwind": F_UPWIND}

# ---- driver codes (prm[P_DRIVER]; informational, S is computed by the engine) ---------------
DRIVER_CODES: dict[str, int] = {"A": 0, "B": 1, "C": 2, "P": 3, "G": 4}

# ---- slots of the parameter vector prm (float64) ---------------------------------------------
P_MODEL = 0  #: closure code M_*
P_FLUX = 1  #: face-flux code F_*
P_DT_TARGET = 2  #: target subcycle length t_int, s (segregation.dt; read by the engine)
P_FILL_MIN = 3  #: θ_min, minimum fill fraction of an active cell
P_SAFETY = 4  #: safety factor (< 1) on the stable FV step Δt_c
P_D_SMALL = 5  #: d_s, m
P_D_LARGE = 6  #: d_l, m
P_RHO_BULK = 7  #: ρ = f ρ_s, kg/m³
P_C_D = 8  #: c_D, 1/s
P_ETA = 9  #: η, m²/s² (D = η/c_D)
P_B_KS = 10  #: b^{k,s}
P_B_CS = 11  #: b^{c,s}
P_GX = 12  #: g·e_x = g sin θ, m/s²
P_GY = 13  #: g·e_y = −g cos θ, m/s²
P_Q = 14  #: Gray–Thornton q (m/s, or dimensionless when shear-scaled)
P_Q_SHEAR = 15  #: 1: w_y = −q γ̇ d̄; 0: w_y = −q
P_DIFF = 16  #: Gray–Thornton diffusivity, m²/s
P_FAN_S = 17  #: Fan et al. S_r, m
P_FAN_D = 18  #: Fan et al. D prefactor (D = coeff γ̇ d̄²)
P_KAPPA = 19  #: κ (engine only: S is passed in already scaled)
P_KAPPA_T = 20  #: κ_T of driver B (engine only)
P_DRIVER = 21  #: driver code 0 = A, 1 = B, 2 = C (engine only)
P_HC = 22  #: resolved concentration-cell size h_c, m
P_LH_CSEG = 23  #: liu_henann C_seg (shear-rate-gradient term)
P_LH_CP = 24  #: liu_henann C_p (pressure-gradient term)
P_LH_CDIFF = 25  #: liu_henann C_diff (D = C_diff γ̇ d̄²)
N_PARAMS = 26

#: default safety factor on the stability bound of the explicit FV step
DEFAULT_SAFETY = 0.9


def make_params(
    model: str = "hill_tan_reduced",
    *,
    flux: str = "sg",
    dt_target: float = 1.0e-3,
    fill_min: float = 0.5,
    safety: float = DEFAULT_SAFETY,
    d_small: float = 2.0e-3,
    d_large: float = 3.0e-3,
    rho_bulk: float = 1590.0,
    c_D: float = 6.8,
    eta: float = 1.11e-5,
    b_k_small: float = 0.39,
    b_c_small: float = 0.0,
    gravity_xy: tuple[float, float] = (0.0, -9.81),
    q: float = 0.01,
    q_shear_scaled: bool = False,
    diffusivity: float = 1.6e-6,
    fan_S: float = 1.0e-4,
    fan_D_coeff: float = 0.042,
    kappa: float = 1.0,
    kappa_T: float = 0.3,
    driver: str = "A",
    hc: float = 2.5e-4,
    lh_C_seg: float = 0.2,
    lh_C_p: float = 0.2,
    lh_C_diff: float = 0.042,
) -> np.ndarray:
    """Build the parameter vector ``prm`` from explicit values (tests, scripts).

    Symbols: b^{k,s} = ``b_k_small``, b^{c,s} = ``b_c_small``, c_D, η = ``eta``, ρ = ``rho_bulk``.
    """
    if model not in MODEL_CODES:
        raise ValueError(f"unknown segregation model {model!r}; allowed: {', '.join(MODEL_CODES)}")
    if flux not in FLUX_CODES:
        raise ValueError(f"unknown face flux {flux!r}; allowed: {', '.join(FLUX_CODES)}")
    if not 0.0 < safety <= 1.0:
        raise ValueError(f"safety = {safety} must be in (0, 1]")
    prm = np.zeros(N_PARAMS, dtype=np.float64)
    prm[P_MODEL] = MODEL_CODES[model]
    prm[P_FLUX] = FLUX_CODES[flux]
    prm[P_DT_TARGET] = dt_target
    prm[P_FILL_MIN] = fill_min
    prm[P_SAFETY] = safety
    prm[P_D_SMALL] = d_small
    prm[P_D_LARGE] = d_large
    prm[P_RHO_BULK] = rho_bulk
    prm[P_C_D] = c_D
    prm[P_ETA] = eta
    prm[P_B_KS] = b_k_small
    prm[P_B_CS] = b_c_small
    prm[P_GX] = gravity_xy[0]
    prm[P_GY] = gravity_xy[1]
    prm[P_Q] = q
    prm[P_Q_SHEAR] = 1.0 if q_shear_scaled else 0.0
    prm[P_DIFF] = diffusivity
    prm[P_FAN_S] = fan_S
    prm[P_FAN_D] = fan_D_coeff
    prm[P_KAPPA] = kappa
    prm[P_KAPPA_T] = kappa_T
    prm[P_DRIVER] = DRIVER_CODES[driver]
    prm[P_HC] = hc
    prm[P_LH_CSEG] = lh_C_seg
    prm[P_LH_CP] = lh_C_p
    prm[P_LH_CDIFF] = lh_C_diff
    return prm


def conc_cell_size(cfg: Any) -> float:
    """Resolved concentration-cell size h_c: ``segregation.cell_size`` or half the MPM cell."""
    hc = float(cfg.segregation.cell_size)
    return hc if hc > 0.0 else 0.5 * float(cfg.grid.cell_size)


def effective_driver(cfg: Any) -> str:
    """The driver S a configuration's closure uses (``materials.params.effective_driver``)."""
    from ..materials.params import effective_driver as _eff

    return _eff(cfg)


def pack_params(cfg: Any, gravity_xy: tuple[float, float] | np.ndarray) -> np.ndarray:
    """Parameter vector ``prm`` (float64, slots ``P_*``) from a ``segmpm.config.Config``.

    ``gravity_xy`` is the gravity vector g = (g sin θ, −g cos θ) in the slope frame (m/s²), as used
    by the engine (it may include a ramp; pass the full value).
    """
    s = cfg.segregation
    mix = cfg.mixture
    mat = cfg.material
    gx, gy = float(gravity_xy[0]), float(gravity_xy[1])
    return make_params(
        s.model,
        flux=s.flux,
        dt_target=s.dt,
        fill_min=s.fill_min,
        d_small=mix.d_small,
        d_large=mix.d_large,
        rho_bulk=mat.solid_fraction * mat.grain_density,
        c_D=s.c_D,
        eta=s.eta,
        b_k_small=s.b_k_small,
        b_c_small=s.b_c_small,
        gravity_xy=(gx, gy),
        q=s.q,
        q_shear_scaled=s.q_shear_scaled,
        diffusivity=s.diffusivity,
        fan_S=s.fan_S,
        fan_D_coeff=s.fan_D_coeff,
        kappa=s.kappa,
        kappa_T=s.kappa_T,
        driver=effective_driver(cfg),
        hc=conc_cell_size(cfg),
        lh_C_seg=s.lh_C_seg,
        lh_C_p=s.lh_C_p,
        lh_C_diff=s.lh_C_diff,
    )


# ---- compiled face functions -----------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def face_velocity_diffusivity(
    prm: np.ndarray,
    s_a: float,
    s_b: float,
    g_a: float,
    g_b: float,
    dbar_a: float,
    dbar_b: float,
    hc: float,
    normal_y: int,
) -> tuple[float, float]:
    """Face-normal segregation velocity w (m/s) and diffusivity D (m²/s) of the closure in prm.

    The face goes from cell a to cell b along +n (n = e_y if ``normal_y`` else e_x); s = time-averaged
    driving stress S (Pa), g = shear rate γ̇ (1/s), dbar = mean diameter d̄ (m) of the two cells.
    """
    model = int(prm[P_MODEL])
    if model == M_HILL_TAN_REDUCED:
        # seed Eq. 6: small grains move toward lower S when b^{k,s} > 0
        dsdn = (s_b - s_a) / hc
        w = -prm[P_B_KS] / (prm[P_C_D] * prm[P_RHO_BULK]) * dsdn
        return w, prm[P_ETA] / prm[P_C_D]
    if model == M_HILL_TAN_FULL:
        dsdn = (s_b - s_a) / hc
        gn = prm[P_GY] if normal_y == 1 else prm[P_GX]
        w = (prm[P_B_CS] - prm[P_B_KS]) / (prm[P_C_D] * prm[P_RHO_BULK]) * dsdn
        w -= prm[P_B_CS] / prm[P_C_D] * gn
        return w, prm[P_ETA] / prm[P_C_D]
    if model == M_GRAY_THORNTON:
        w = 0.0
        if normal_y == 1:
            if prm[P_Q_SHEAR] != 0.0:
                w = -prm[P_Q] * 0.5 * (g_a + g_b) * 0.5 * (dbar_a + dbar_b)
            else:
                w = -prm[P_Q]
        return w, prm[P_DIFF]
    if model == M_LIU_HENANN:
        # s: time-averaged pressure p (driver P), g: shear rate
        gdot = 0.5 * (g_a + g_b)
        pf = 0.5 * (s_a + s_b)
        dbar = 0.5 * (dbar_a + dbar_b)
        w = -prm[P_LH_CSEG] * (g_b - g_a) / hc
        if pf > 0.0:
            w += prm[P_LH_CP] * gdot / pf * (s_b - s_a) / hc
        return w * dbar * dbar, prm[P_LH_CDIFF] * gdot * dbar * dbar
    if model == M_FAN2014:
        gdot = 0.5 * (g_a + g_b)
        dbar = 0.5 * (dbar_a + dbar_b)
        w = -prm[P_FAN_S] * gdot if normal_y == 1 else 0.0
        return w, prm[P_FAN_D] * gdot * dbar * dbar
    return 0.0, 0.0


@njit(cache=True, error_model="numpy")
def bernoulli(x: float) -> float:
    """B(x) = x/(eˣ − 1), B(0) = 1 (the Bernoulli function of the Scharfetter–Gummel flux)."""
    if abs(x) < 1e-10:
        return 1.0 - 0.5 * x
    return x / np.expm1(x)


@njit(cache=True, error_model="numpy")
def face_rates(w: float, d: float, hc: float, flux_kind: int) -> tuple[float, float]:
    """Coefficients (a, b) of the face flux F = a φ_a(1−φ_b) − b φ_b(1−φ_a) (positive along +n).

    Scharfetter–Gummel: a = (D/h_c) B(−P), b = (D/h_c) B(P) with the cell Péclet number
    P = w h_c/D, so a − b = w exactly and the zero-flux state has logit φ_b − logit φ_a = P.
    D = 0 gives the upwind limit a = max(w, 0), b = max(−w, 0). The upwind + central switch uses
    a = max(w, 0) + D/h_c, b = max(−w, 0) + D/h_c. Both a, b ≥ 0 and max(a, b) ≤ |w| + D/h_c,
    which is what the stability bound uses.
    """
    wp = w if w > 0.0 else 0.0
    wm = -w if w < 0.0 else 0.0
    if flux_kind == F_UPWIND:
        return wp + d / hc, wm + d / hc
    if d <= 0.0:
        return wp, wm
    p = w * hc / d
    if abs(p) > 700.0:
        # exp overflow: B(−P) → P, B(P) → 0 to double precision
        return wp, wm
    return d / hc * bernoulli(-p), d / hc * bernoulli(p)
