"""Material parameters as one float64 record (slots named below) for the compiled kernels.

The engine selects the constitutive law by the integer in slot ``M_KIND`` at set-up; the string
names of the configuration never reach compiled code.
"""

from __future__ import annotations

import numpy as np

from ..config import Config

KIND_LINEAR_ELASTIC = 0
KIND_FEI2016 = 1
#: Jiang–Liu elasticity (the Fei et al. energy) with the nonlocal granular fluidity flow rule
#: γ̇ᵖ = g μ instead of the yield cap and σ^d (``material.rheology = "nonlocal"``, docs/model.md)
KIND_FEI2016_NGF = 2

DRIVER_A = 0  # S = μ_d(I) p_e   (seed Eq. 4 read as a scalar; docs/segregation.md §1)
DRIVER_B = 1  # S = κ_T ρ (γ̇ d̄)²
DRIVER_C = 2  # S = −σ^d_yy (literal seed; ≈ 0 in steady shear, diagnostic)
DRIVER_P = 3  # S = p_e (the pressure: the Liu–Singh–Henann closure's pressure-gradient driver)
DRIVER_G = 4  # S = κ_g ρ (g d̄)² (kinetic stress from the fluidity, Zhang & Kamrin 2017)

(
    M_KIND,
    M_RHO_S,  # ρ_s, grain density
    M_F,  # f, solid fraction of the stress-free state
    M_A,  # A (already multiplied by stiffness_scale)
    M_C,  # C = 5 q_φ² A
    M_QPHI,  # q_φ
    M_MU_A,  # a of μ_d = a I^b
    M_MU_B,  # b
    M_RC,  # r_c, yield cap ratio
    M_SDF,  # sigma_d_factor
    M_GFLOOR,  # shear-rate floor for b < 1
    M_ZETA,  # bulk viscosity as a fraction of ρ c h
    M_H,  # MPM cell size h (bulk viscosity)
    M_DS,  # d_s
    M_DL,  # d_l
    M_DRIVER,  # segregation driver (DRIVER_*)
    M_KAPPA,  # κ, scale on S
    M_KAPPA_T,  # κ_T of driver B
    M_LAMBDA,  # linear elastic λ
    M_MU,  # linear elastic μ (shear modulus)
    # derived constants, so that the compiled update multiplies instead of dividing
    M_CAPR,  # r_c / q_φ
    M_IRHO0,  # 1 / (f ρ_s)
    M_CW,  # 3.75 A + 2 C: ρ c² = (3.75 A + 2 C) √I₁
    # nonlocal granular fluidity (KIND_FEI2016_NGF)
    M_MU_S,  # μ_s, static friction of the NGF
    M_NGF_B,  # b of g_loc = √(p/ρ_s d̄²)(μ − μ_s)/(b μ), i.e. μ = μ_s + b I locally
    M_NGF_A,  # A, nonlocal amplitude (cooperativity length ξ = A d̄/√|μ − μ_s|)
    M_T0,  # t₀, fluidity time scale, s
    M_KAPPA_G,  # κ_g of driver G (= 1/F² of δv = g d̄ / F)
    M_FLU_DT,  # target interval of the fluidity update (mpm.fluidity), s
    M_PFLOOR,  # p_min of the fluidity's local term √(ρ_s d̄²/max(p, p_min)), Pa
    M_NSLOTS,
) = range(31)


DRIVER_CODES = {"A": DRIVER_A, "B": DRIVER_B, "C": DRIVER_C, "P": DRIVER_P, "G": DRIVER_G}

#: closures that fix their own driver S (the ``segregation.driver`` key is not used by them)
CLOSURE_DRIVERS = {"liu_henann": "P", "hill_tan_fluidity": "G"}


def effective_driver(cfg: Config) -> str:
    """The driver S the engine computes: the closure's own (``CLOSURE_DRIVERS``) or
    ``segregation.driver``."""
    return CLOSURE_DRIVERS.get(cfg.segregation.model, cfg.segregation.driver)


def fluidity_pressure_floor(cfg: Config) -> float:
    """p_min = n f ρ_s g d̄₀ with n = ``material.fluidity_floor_layers``: the weight of n grain
    layers of the initial mixture (d̄₀ = φ_s0 d_s + (1 − φ_s0) d_l), Pa."""
    m, mix = cfg.material, cfg.mixture
    d0 = mix.phi_small_initial * mix.d_small + (1.0 - mix.phi_small_initial) * mix.d_large
    return m.fluidity_floor_layers * m.solid_fraction * m.grain_density * cfg.time.gravity * d0


def pack_material(cfg: Config) -> np.ndarray:
    """Build the material record from a configuration."""
    m = cfg.material
    prm = np.zeros(M_NSLOTS, dtype=np.float64)
    if m.model == "fei2016":
        prm[M_KIND] = KIND_FEI2016_NGF if m.rheology == "nonlocal" else KIND_FEI2016
    else:
        prm[M_KIND] = KIND_LINEAR_ELASTIC
    prm[M_RHO_S] = m.grain_density
    prm[M_F] = m.solid_fraction
    A = m.A * m.stiffness_scale
    prm[M_A] = A
    prm[M_C] = 5.0 * m.q_phi**2 * A
    prm[M_QPHI] = m.q_phi
    prm[M_MU_A] = m.a
    prm[M_MU_B] = m.b
    prm[M_RC] = m.cap_ratio
    prm[M_SDF] = m.sigma_d_factor
    prm[M_GFLOOR] = m.shear_rate_floor
    prm[M_ZETA] = m.bulk_viscosity
    prm[M_H] = cfg.grid.cell_size
    prm[M_DS] = cfg.mixture.d_small
    prm[M_DL] = cfg.mixture.d_large
    prm[M_DRIVER] = DRIVER_CODES[effective_driver(cfg)]
    prm[M_KAPPA] = cfg.segregation.kappa
    prm[M_KAPPA_T] = cfg.segregation.kappa_T
    prm[M_CAPR] = m.cap_ratio / m.q_phi
    prm[M_IRHO0] = 1.0 / (m.solid_fraction * m.grain_density)
    prm[M_CW] = 3.75 * A + 2.0 * prm[M_C]
    prm[M_MU_S] = m.static_friction
    prm[M_NGF_B] = m.rate_sensitivity
    prm[M_NGF_A] = m.nonlocal_amplitude
    prm[M_T0] = m.fluidity_time
    prm[M_FLU_DT] = m.fluidity_dt if m.fluidity_dt > 0 else 0.25 * m.fluidity_time
    prm[M_KAPPA_G] = cfg.segregation.kappa_g
    prm[M_PFLOOR] = fluidity_pressure_floor(cfg)
    E, nu = m.youngs_modulus, m.poisson_ratio
    prm[M_LAMBDA] = E * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    prm[M_MU] = E / (2.0 * (1.0 + nu))
    return prm
