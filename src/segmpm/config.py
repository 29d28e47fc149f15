"""Configuration of a run: pydantic schema, TOML loading, ``--set`` overrides.

Every key lives in one of the sections of the public interface (README, "Configuration"):
``scenario``, ``geometry``, ``grid``, ``material``, ``mixture``, ``segregation``, ``boundary``,
``time``, ``output``.
All quantities are SI. Unknown keys are rejected. The built-in default (``DEFAULT_PRESET``) is the
seed's chute case (Fei, Sun, Hill & Zhou 2017, §4) with the grain-calibrated nonlocal model; the
seed's own reduced local model is the preset ``chute_seed`` (README).
"""

from __future__ import annotations

import copy
import math
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

PositiveFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegFloat = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Fraction = Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)]

#: Largest number of material points a run may allocate (memory guard, ~1 kB each with grids).
MAX_PARTICLES = 20_000_000
#: Largest number of background-grid nodes.
MAX_NODES = 50_000_000


class ConfigError(ValueError):
    """Invalid configuration. ``str(err)`` is a one-paragraph message naming key, value and range."""


#: material points per cell along one axis.
PointsPerCell = Annotated[int, Field(ge=1, le=6)]


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class ScenarioConfig(_Section):
    """What is simulated; each kind builds its particles and boundaries from the other sections."""

    kind: Literal["chute", "collapse", "bar", "box"] = "chute"
    #: bar: initial velocity amplitude v0 of the first mode, m/s; box: uniform velocity (x), m/s.
    velocity: Annotated[float, Field(ge=-1e3, le=1e3, allow_inf_nan=False)] = 1e-3
    #: ``"mpm"``: the 2-D material point method; ``"column"``: the 1-D depth-resolved model of an
    #: x-uniform layer (chute only) with the same constitutive, fluidity and segregation kernels
    #: (docs/column.md); it writes the same profiles and run files, no particle snapshots.
    solver: Literal["mpm", "column"] = "mpm"


class GeometryConfig(_Section):
    """Domain geometry. Chute: periodic strip ``length`` × ``depth`` on a slope (docs/model.md)."""

    #: incline angle θ, degrees (the slope frame: x downslope, y normal to the base).
    slope_deg: Annotated[float, Field(ge=0, lt=90, allow_inf_nan=False)] = 26.0
    #: initial layer depth H normal to the base, m (chute, box, bar thickness).
    depth: Annotated[float, Field(gt=0, le=100, allow_inf_nan=False)] = 0.0373
    #: channel width W between the sidewalls, m (only enters the sidewall friction).
    width: Annotated[float, Field(gt=0, le=1e3, allow_inf_nan=False)] = 0.022
    #: periodic length L_x (chute, box) or bar length, or domain length (collapse), m.
    length: Annotated[float, Field(gt=0, le=1e3, allow_inf_nan=False)] = 0.012
    #: collapse: initial column width L0 and height H0, m.
    column_width: Annotated[float, Field(gt=0, le=100, allow_inf_nan=False)] = 0.02
    column_height: Annotated[float, Field(gt=0, le=100, allow_inf_nan=False)] = 0.04
    #: 2: plane strain (x downslope, y normal to the base); 3: x downslope, y normal, z across
    #: the channel, with resolved sidewalls at z = 0 and z = ``width`` (docs/architecture.md;
    #: the 3-D engine runs chute and collapse with the local rheology).
    dimension: Literal[2, 3] = 2
    #: 3-D chute: model only 0 ≤ z ≤ width/2, with a symmetry plane at mid-width.
    mirror: bool = False
    #: empty space kept above the material for the grid, as a multiple of the initial height.
    headroom: Annotated[float, Field(ge=0.05, le=10, allow_inf_nan=False)] = 0.3


class GridConfig(_Section):
    """MPM background grid (docs/model.md §2)."""

    #: background cell size h, m.
    cell_size: Annotated[float, Field(gt=0, le=10, allow_inf_nan=False)] = 5.0e-4
    #: material points per cell and direction (2 → 4 points per cell in 2-D, spacing h/2), or one
    #: count per axis, [x, y] in 2-D and [x, y, z] in 3-D (e.g. [2, 3, 3]: docs/model.md §2).
    particles_per_cell: PointsPerCell | list[PointsPerCell] = 2
    #: shape functions: quadratic B-splines.
    shape: Literal["bspline2"] = "bspline2"
    #: particle–grid transfer: "aflip" (APIC affine momentum with a FLIP velocity update, the
    #: default; docs/model.md explains why), "apic", or "flip" (MUSL with a FLIP/PIC blend).
    transfer: Literal["aflip", "apic", "flip"] = "aflip"
    #: FLIP fraction α of the velocity update (transfer = "aflip" or "flip").
    flip_fraction: Fraction = 0.99
    #: volumetric smoothing: each point's volumetric rate tr L replaced by its mass-weighted
    #: average over the grid (mapped to the nodes and back), so that the points of a cell share
    #: one rate of J. It removes the null mode of 2 points per cell and axis (alternate point
    #: rows compressed and dilated) that grows in 3-D near the free surface (docs/model.md §2,
    #: "Volumetric smoothing"). "auto": on for the nonlocal rheology in 3-D, where it was shown
    #: to help, else off; "on" needs geometry.dimension = 3.
    volumetric_smoothing: Literal["auto", "on", "off"] = "auto"
    #: the MPM engine: "auto" and "generic" (the same: the dimension-generic engine,
    #: segmpm.engine, in 2-D and 3-D, the column solver included). The former plane-strain
    #: engine ("production") was removed on 2026-12-07 (docs/architecture.md, "One engine").
    engine: Literal["auto", "generic"] = "auto"

    @model_validator(mode="before")
    @classmethod
    def _removed_engine(cls, data: Any) -> Any:
        if isinstance(data, dict) and data.get("engine") == "production":
            raise ValueError(
                "grid.engine = 'production' (the former plane-strain engine) was removed on "
                "2026-12-07: every run is on the dimension-generic engine, which gives its 2-D "
                "results to round-off; allowed: 'auto', 'generic'"
            )
        return data

    #: threads of the compiled loop: "auto" (one below 20 000 points, else the cores this process
    #: may use that no other process keeps busy; segmpm.threads) or a count (0 = numba's pool).
    #: Results do not depend on it.
    threads: Annotated[int, Field(ge=0, le=256)] | Literal["auto"] = "auto"

    def points_per_axis(self, dim: int) -> tuple[int, ...]:
        """The points per cell along each of the ``dim`` axes (x, y[, z])."""
        p = self.particles_per_cell
        return (p,) * dim if isinstance(p, int) else tuple(p)

    def point_spacing(self, dim: int) -> tuple[float, ...]:
        """The lattice spacing of the material points along each axis, h / n_a."""
        return tuple(self.cell_size / n for n in self.points_per_axis(dim))


class MaterialConfig(_Section):
    """Constitutive model: Fei et al. 2016 (docs/model.md §1) or linear elasticity (tests)."""

    model: Literal["fei2016", "linear_elastic"] = "fei2016"
    #: flow rule: "local" (the seed's yield cap + μ(I) dissipative stress, μ = q_c + a I^b) or
    #: "nonlocal" (nonlocal granular fluidity: γ̇ᵖ = g μ with the fluidity g of the dynamic
    #: Kamrin–Henann equation; it replaces the cap and σ^d, docs/model.md "Nonlocal rheology").
    rheology: Literal["local", "nonlocal"] = "local"
    #: nonlocal: μ_s, the static friction of the fluidity model (g_loc = 0 for μ ≤ μ_s).
    static_friction: Annotated[float, Field(gt=0, le=2, allow_inf_nan=False)] = 0.3819
    #: nonlocal: b of g_loc = √(p/ρ_s d̄²)(μ − μ_s)/(b μ), i.e. the local law μ = μ_s + b I.
    rate_sensitivity: Annotated[float, Field(gt=0, le=100, allow_inf_nan=False)] = 0.9377
    #: nonlocal: the nonlocal amplitude A (cooperativity length ξ = A d̄ / √|μ − μ_s|); 0 is the
    #: local limit.
    nonlocal_amplitude: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)] = 0.48
    #: nonlocal: t₀ of t₀ ∂g/∂t = A² d̄² ∇²g − (μ_s − μ) g − b μ √(ρ_s d̄²/p) g², s.
    fluidity_time: Annotated[float, Field(gt=0, le=10, allow_inf_nan=False)] = 1.0e-3
    #: nonlocal: the g² term's √(ρ_s d̄²/p) uses max(p, p_min), p_min the weight of this many
    #: grain layers, f ρ_s g d̄₀ (the continuum ends one grain below the free surface, where
    #: p → 0 makes the term singular; docs/model.md). 0: no floor (the local limit).
    fluidity_floor_layers: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)] = 1.0
    #: nonlocal: target interval of the fluidity update, s (0 = t₀/4); it is never shorter than
    #: one MPM step.
    fluidity_dt: Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)] = 0.0
    #: grain (material) density ρ_s, kg/m³.
    grain_density: Annotated[float, Field(gt=0, le=1e5, allow_inf_nan=False)] = 2650.0
    #: solid volume fraction f of the mixture (bulk density ρ = f ρ_s).
    solid_fraction: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = 0.6
    #: Jiang–Liu bulk coefficient A, Pa.
    A: Annotated[float, Field(gt=0, le=1e13, allow_inf_nan=False)] = 1.79e9
    #: q_φ, the friction coefficient at loss of elastic convexity.
    q_phi: Annotated[float, Field(gt=0, le=2, allow_inf_nan=False)] = 0.38
    #: μ_d(I) = a I^b.
    a: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)] = 0.46
    b: Annotated[float, Field(gt=0, le=2, allow_inf_nan=False)] = 1.0
    #: factor on A and C (stiffness reduction, docs/model.md §1, "Stiffness scale").
    stiffness_scale: Annotated[float, Field(gt=0, le=1e3, allow_inf_nan=False)] = 1.0
    #: r_c, yield cap on the deviatoric elastic strain at r_c I1/q_φ (docs/model.md §1, step 4).
    cap_ratio: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = 0.95
    #: factor on σ^d (1 = standard μ(I) normalisation, 0.5 = the seed's literal formula).
    sigma_d_factor: Annotated[float, Field(ge=0, le=10, allow_inf_nan=False)] = 1.0
    #: floor on the shear rate in μ_d for b < 1, 1/s.
    shear_rate_floor: Annotated[float, Field(gt=0, le=1e3, allow_inf_nan=False)] = 1e-6
    #: bulk viscosity ζ_b as a fraction of ρ c h (docs/model.md §1, step 9), 0 disables; the
    #: column model uses at least ``column.COLUMN_BULK_VISCOSITY`` (docs/column.md).
    bulk_viscosity: Annotated[float, Field(ge=0, le=10, allow_inf_nan=False)] = 0.0
    #: initial state: "geostatic" (I1 from the oedometric law under the initial load: a lateral
    #: stress ratio K₀ < 1), "isotropic" (the same load as an isotropic pressure, no deviatoric
    #: stress: the relaxed state the nonlocal flow rule starts from, docs/model.md) or
    #: "stress_free".
    initial_state: Literal["geostatic", "isotropic", "stress_free"] = "geostatic"
    #: linear elastic: Young's modulus E (Pa) and Poisson's ratio ν.
    youngs_modulus: Annotated[float, Field(gt=0, le=1e13, allow_inf_nan=False)] = 1.0e6
    poisson_ratio: Annotated[float, Field(ge=0, lt=0.5, allow_inf_nan=False)] = 0.0


class MixtureConfig(_Section):
    """Binary mixture of small and large grains (docs/segregation.md §1)."""

    d_small: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = 2.0e-3
    d_large: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = 3.0e-3
    #: φ^s at t = 0, uniform.
    phi_small_initial: Fraction = 0.5

    @model_validator(mode="after")
    def _sizes(self) -> MixtureConfig:
        if self.d_small > self.d_large:
            raise ValueError(
                f"mixture.d_small = {self.d_small} must not exceed mixture.d_large = {self.d_large}"
            )
        return self


class SegregationConfig(_Section):
    """Species transport on the extra Eulerian grid (docs/segregation.md)."""

    #: closure: the seed's reduced Hill–Tan Eq. 6 (default), the full vector Eq. 1, Gray–Thornton,
    #: Fan et al. 2014, or none.
    #: "liu_henann": the relative flux driven by shear-rate and pressure gradients (Liu, Singh &
    #: Henann 2023; Singh, Liu & Henann 2024); "hill_tan_fluidity": the Hill–Tan flux (as
    #: hill_tan_full) with the kinetic stress σ^k = κ_g ρ (g d̄)² of the fluidity (nonlocal only).
    model: Literal[
        "hill_tan_reduced", "hill_tan_full", "hill_tan_fluidity", "liu_henann", "gray_thornton",
        "fan2014", "none",
    ] = "hill_tan_reduced"  # fmt: skip
    #: driver S of the kinetic-stress term (docs/segregation.md): A = μ_d p, B = κ_T ρ(γ̇ d̄)²,
    #: C = σ^d_yy, P = p_e, G = κ_g ρ (g d̄)² (nonlocal only). liu_henann always uses P and
    #: hill_tan_fluidity G. Default B: it reproduces our DEM reference of the seed case better
    #: than A (docs/validation.md).
    driver: Literal["A", "B", "C", "P", "G"] = "B"
    #: scale factor κ on S.
    kappa: Annotated[float, Field(ge=0, le=1e3, allow_inf_nan=False)] = 1.0
    #: κ_T of driver B.
    kappa_T: Annotated[float, Field(ge=0, le=1e3, allow_inf_nan=False)] = 0.3
    #: linear drag coefficient c_D, 1/s.
    c_D: Annotated[float, Field(gt=0, le=1e6, allow_inf_nan=False)] = 6.8
    #: η, m²/s² (D = η / c_D).
    eta: Annotated[float, Field(ge=0, le=1e3, allow_inf_nan=False)] = 1.11e-5
    #: kinetic-stress partition b^{k,s} (b^{k,l} = −b^{k,s}).
    b_k_small: Annotated[float, Field(ge=-4, le=4, allow_inf_nan=False)] = 0.39
    #: contact-stress partition b^{c,s} (0 = the seed's ψ^{c,i} = φ^i).
    b_c_small: Annotated[float, Field(ge=-4, le=4, allow_inf_nan=False)] = 0.0
    #: Gray–Thornton percolation speed q (m/s) and diffusivity (m²/s); q_shear_scaled uses q γ̇ d̄ instead.
    q: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)] = 0.01
    q_shear_scaled: bool = False
    diffusivity: Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)] = 1.6e-6
    #: Fan et al. 2014: segregation velocity factor S_r (m) in w = S_r γ̇ (1-φ), and the D prefactor.
    fan_S: Annotated[float, Field(ge=0, le=1, allow_inf_nan=False)] = 1.0e-4
    fan_D_coeff: Annotated[float, Field(ge=0, le=10, allow_inf_nan=False)] = 0.042
    #: κ_g of σ^k = κ_g ρ (g d̄)² (driver G): 1/F² of the fluctuation speed δv = g d̄ / F.
    kappa_g: Annotated[float, Field(ge=0, le=1e6, allow_inf_nan=False)] = 1.0
    #: liu_henann: w = d̄² (−C_seg ∂γ̇/∂n + C_p (γ̇/p) ∂p/∂n) (positive along n, small grains),
    #: D = C_diff γ̇ d̄² (docs/segregation.md).
    lh_C_seg: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)] = 0.2
    lh_C_p: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)] = 0.2
    lh_C_diff: Annotated[float, Field(ge=0, le=10, allow_inf_nan=False)] = 0.042
    #: extra-grid cell size h_c, m (0 = half the MPM cell).
    cell_size: Annotated[float, Field(ge=0, le=10, allow_inf_nan=False)] = 0.0
    #: minimum fill fraction θ_min of an active concentration cell.
    fill_min: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = 0.5
    #: face flux: exponentially fitted Scharfetter–Gummel (default) or upwind + central.
    flux: Literal["sg", "upwind"] = "sg"
    #: target length of one concentration step, s (it is also limited by stability).
    dt: Annotated[float, Field(gt=0, le=10, allow_inf_nan=False)] = 1.0e-3


class BoundaryConfig(_Section):
    """Boundaries (docs/model.md §2, "Boundaries" and "Sidewall friction")."""

    #: μ_w of the sidewall body force −(2 μ_w K_w p / W) v/|v| (0 disables it).
    sidewall_friction: Annotated[float, Field(ge=0, le=10, allow_inf_nan=False)] = 0.3
    #: a sidewall friction that grows with the sliding speed u (the width-averaged velocity),
    #: μ_w(u) = μ_w0 + (μ_w − μ_w0) u/(u + u_w), μ_w0 = ``sidewall_friction_slow``,
    #: u_w = ``sidewall_slip_speed`` (m/s; 0 = the constant Coulomb μ_w). The mobilised friction
    #: of the grains on a flat wall measured in DEM has this form (docs/calibration.md).
    sidewall_friction_slow: Annotated[float, Field(ge=0, le=10, allow_inf_nan=False)] = 0.0
    sidewall_slip_speed: Annotated[float, Field(ge=0, le=100, allow_inf_nan=False)] = 0.0
    #: K_w, ratio of the wall normal stress to the pressure.
    wall_normal_stress_ratio: Annotated[float, Field(ge=0, le=10, allow_inf_nan=False)] = 1.0
    #: base (y = 0): no-slip (rough), free-slip, or Coulomb friction.
    base: Literal["noslip", "slip", "friction"] = "noslip"
    base_friction: Annotated[float, Field(ge=0, le=10, allow_inf_nan=False)] = 0.5
    #: walls at x = 0 and x = length in non-periodic scenarios (collapse, bar).
    walls: Literal["noslip", "slip", "friction"] = "slip"
    wall_friction: Annotated[float, Field(ge=0, le=10, allow_inf_nan=False)] = 0.3
    #: image (mirror) nodes behind no-slip walls: second-order wall kinematics (docs/model.md);
    #: false gives plain fixed nodes, first order in h at the wall.
    wall_images: bool = True
    #: time over which the sidewall friction and the tangential gravity ramp on, s (0 = at once).
    ramp_time: Annotated[float, Field(ge=0, le=1e3, allow_inf_nan=False)] = 0.0


class TimeConfig(_Section):
    """Time integration (docs/model.md §1, "Wave speed and time step")."""

    #: simulated time to reach, s.
    end: Annotated[float, Field(gt=0, le=1e5, allow_inf_nan=False)] = 20.0
    #: Courant number of the time step Δt = CFL h / max(c + |v|).
    cfl: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = 0.4
    #: the column model's Courant number c Δt/Δy on its element Δy (``scenario.solver =
    #: "column"``; docs/column.md; stable below 1 with the column's bulk-viscosity floor).
    column_courant: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = 0.9
    #: C_ν of the viscous limit Δt ≤ C_ν h²/(2 max ν); explicit diffusion in 2-D is stable for
    #: C_ν < 0.5, so it is kept apart from the Courant number.
    viscous_number: Annotated[float, Field(gt=0, lt=0.5, allow_inf_nan=False)] = 0.4
    #: largest time step, s.
    dt_max: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = 1.0e-3
    #: the run fails (exit 3) if Δt falls below this, s.
    dt_min: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = 1.0e-12
    #: compiled steps between Python's looks at the state (progress, NaN check, outputs).
    chunk_steps: Annotated[int, Field(ge=1, le=10_000_000)] = 2000
    #: gravitational acceleration, m/s².
    gravity: Annotated[float, Field(ge=0, le=1e3, allow_inf_nan=False)] = 9.81


class OutputConfig(_Section):
    """What a run writes (README, "Outputs")."""

    #: output directory (``--out`` overrides it).
    dir: Annotated[str, Field(min_length=1, max_length=4096)] = "segmpm-out"
    #: times at which depth profiles are written, s.
    profile_times: list[Annotated[float, Field(ge=0, allow_inf_nan=False)]] = [
        0.0,
        0.5,
        1.0,
        2.0,
        5.0,
        10.0,
        20.0,
    ]
    #: thickness of the depth-profile bins, m.
    profile_bin: Annotated[float, Field(gt=0, le=100, allow_inf_nan=False)] = 5.0e-4
    #: simulated time between checkpoints, s (0 = only at the end and on interrupt).
    checkpoint_interval: Annotated[float, Field(ge=0, le=1e5, allow_inf_nan=False)] = 1.0
    #: particle snapshots (VTK) at the profile times.
    fields: bool = True
    #: PNG figures at the end.
    figures: bool = True
    #: progress bar on stderr.
    progress: bool = True

    @model_validator(mode="after")
    def _sorted(self) -> OutputConfig:
        try:
            self.dir.encode("utf-8")
        except UnicodeEncodeError:
            raise ValueError(f"output.dir = {self.dir!r} is not valid UTF-8 text") from None
        if sorted(self.profile_times) != list(self.profile_times):
            raise ValueError("output.profile_times must be in increasing order")
        if len(set(self.profile_times)) != len(self.profile_times):
            raise ValueError("output.profile_times must not repeat a time")
        return self


class Config(_Section):
    """A complete run configuration."""

    scenario: ScenarioConfig = ScenarioConfig()
    geometry: GeometryConfig = GeometryConfig()
    grid: GridConfig = GridConfig()
    material: MaterialConfig = MaterialConfig()
    mixture: MixtureConfig = MixtureConfig()
    segregation: SegregationConfig = SegregationConfig()
    boundary: BoundaryConfig = BoundaryConfig()
    time: TimeConfig = TimeConfig()
    output: OutputConfig = OutputConfig()

    @model_validator(mode="after")
    def _consistency(self) -> Config:
        h = self.grid.cell_size
        g = self.geometry
        kind = self.scenario.kind
        if not h >= 1e-9:
            raise ValueError(
                f"grid.cell_size = {h} is too small: allowed ≥ 1e-9 m (and the memory guard below)"
            )
        if kind in ("chute", "box"):
            n = g.length / h
            if abs(n - round(n)) > 1e-6 * max(1.0, n) or round(n) < 2:
                raise ValueError(
                    f"geometry.length = {g.length} must be a whole number (≥ 2) of grid.cell_size = {h} "
                    f"cells for the periodic direction (got {n:.6g} cells)"
                )
        ppc = self.grid.particles_per_cell
        if not isinstance(ppc, int) and len(ppc) != g.dimension:
            raise ValueError(
                f"grid.particles_per_cell = {ppc} has {len(ppc)} counts for geometry.dimension = "
                f"{g.dimension}; allowed: one integer 1-6, or one per axis ([x, y] in 2-D, "
                "[x, y, z] in 3-D)"
            )
        sx, sy = self.grid.point_spacing(g.dimension)[:2]
        if kind in ("chute", "box", "bar") and g.depth < sy:
            raise ValueError(
                f"geometry.depth = {g.depth} is thinner than one material-point spacing "
                f"({sy}); allowed: depth ≥ cell_size/particles_per_cell (along y)"
            )
        if kind == "collapse" and g.column_width > g.length:
            raise ValueError(
                f"geometry.column_width = {g.column_width} must not exceed geometry.length = {g.length}"
            )
        # Memory guard: estimate the sizes before anything is allocated.
        if kind == "collapse":
            area = g.column_width * g.column_height
            extent_x, extent_y = g.length, g.column_height * (1 + g.headroom)
        else:
            area = g.length * g.depth
            extent_x, extent_y = g.length, g.depth * (1 + g.headroom)
        n_particles = area / (sx * sy)
        n_nodes = (extent_x / h + 5) * (extent_y / h + 5)
        if n_particles > MAX_PARTICLES or n_nodes > MAX_NODES:
            if kind == "collapse":
                dims = (f"geometry.length = {g.length}, geometry.column_width = {g.column_width}, "
                        f"geometry.column_height = {g.column_height}")  # fmt: skip
            else:
                dims = f"geometry.length = {g.length}, geometry.depth = {g.depth}"
            raise ValueError(
                f"grid.cell_size = {h} with {dims} gives about {n_particles:.3g} material points and "
                f"{n_nodes:.3g} grid nodes; allowed at most {MAX_PARTICLES:.3g} points and "
                f"{MAX_NODES:.3g} nodes (about {n_particles * 400 / 1e9:.2g} GB): "
                "increase grid.cell_size or reduce the geometry"
            )
        hc = self.segregation.cell_size
        if hc > 0 and hc > 4 * h:
            raise ValueError(
                f"segregation.cell_size = {hc} must be at most 4 × grid.cell_size = {4 * h}"
            )
        m = self.material
        if m.rheology == "nonlocal":
            if m.model != "fei2016":
                raise ValueError(
                    f"material.rheology = 'nonlocal' needs material.model = 'fei2016' (the "
                    f"Jiang–Liu elasticity it relaxes); got material.model = {m.model!r}"
                )
            q_c = m.q_phi * 2.0 * m.cap_ratio / (1.0 + m.cap_ratio**2)
            if q_c <= m.static_friction:
                raise ValueError(
                    f"material.q_phi = {m.q_phi} (with cap_ratio = {m.cap_ratio}) caps the elastic "
                    f"stress ratio at {q_c:.4g}, not above material.static_friction = "
                    f"{m.static_friction}: a nonlocal flow needs stress ratios above μ_s, so "
                    "q_phi must exceed the largest stress ratio of the flow (e.g. q_phi = 0.6; "
                    'docs/model.md, "Nonlocal rheology")'
                )
        needs_g = self.segregation.model == "hill_tan_fluidity" or (
            self.segregation.driver == "G" and self.segregation.model in
            ("hill_tan_reduced", "hill_tan_full")
        )  # fmt: skip
        if needs_g and m.rheology != "nonlocal":
            raise ValueError(
                f"segregation.model = {self.segregation.model!r} with segregation.driver = "
                f"{self.segregation.driver!r} uses the fluidity g: it needs material.rheology = "
                "'nonlocal'"
            )
        if self.scenario.solver == "column" and kind != "chute":
            raise ValueError(
                f"scenario.solver = 'column' models an x-uniform layer: it needs scenario.kind = "
                f"'chute'; got scenario.kind = {kind!r} (allowed with the column: 'chute')"
            )
        if g.dimension == 3:
            self._check_3d()
        else:
            if self.grid.volumetric_smoothing == "on":
                raise ValueError(
                    "grid.volumetric_smoothing = 'on' needs geometry.dimension = 3 (it is "
                    "measured and tested in 3-D only); allowed in 2-D: 'auto', 'off'"
                )
        if self.time.dt_min >= self.time.dt_max:
            raise ValueError(
                f"time.dt_min = {self.time.dt_min} must be smaller than time.dt_max = {self.time.dt_max}"
            )
        return self

    def _check_generic(self, what: str) -> None:
        """What the engine supports in 3-D today (docs/architecture.md)."""
        need = {
            "scenario.kind": (self.scenario.kind, ("chute", "collapse", "box", "bar")),
            # the column is an x-uniform 2-D layer (a 3-D one would be the same column)
            "scenario.solver": (
                self.scenario.solver,
                ("mpm", "column") if self.geometry.dimension == 2 else ("mpm",),
            ),
            "material.rheology": (self.material.rheology, ("local", "nonlocal")),
        }
        for key, (value, allowed) in need.items():
            if value not in allowed:
                raise ValueError(
                    f"{what} does not support {key} = {value!r} yet; allowed: "
                    + ", ".join(repr(a) for a in allowed)
                )

    def _check_3d(self) -> None:
        """What the 3-D engine supports today (docs/architecture.md, "Status")."""
        g = self.geometry
        h = self.grid.cell_size
        v = math.prod(self.grid.point_spacing(3))  # the volume of one point
        self._check_generic("geometry.dimension = 3")
        if self.scenario.kind == "chute":
            wm = g.width / 2 if g.mirror else g.width
            n = wm / h
            if abs(n - round(n)) > 1e-6 * max(1.0, n) or round(n) < 2:
                raise ValueError(
                    f"geometry.width = {g.width} (mirror = {g.mirror}) must give a whole number "
                    f"(≥ 2) of grid.cell_size = {h} cells across the modelled width (got {n:.6g})"
                )
            pts = g.length * g.depth * wm / v
        elif self.scenario.kind in ("box", "bar"):
            pts = g.length * g.depth * g.width / v
        else:
            pts = 0.785 * g.column_width**2 * g.column_height / v
            if g.column_width > g.length:
                raise ValueError(
                    f"geometry.column_width = {g.column_width} (the column radius in 3-D) must "
                    f"not exceed geometry.length = {g.length}"
                )
        if pts > MAX_PARTICLES:
            raise ValueError(
                f"grid.cell_size = {h} gives about {pts:.3g} material points in 3-D; allowed at "
                f"most {MAX_PARTICLES:.3g}: increase grid.cell_size or reduce the geometry"
            )

    # convenience -------------------------------------------------------------------------
    def to_dict(self) -> dict[str, Any]:
        """The fully resolved configuration as plain Python data (TOML-serialisable)."""
        return self.model_dump(mode="json")

    def to_toml(self) -> str:
        """The fully resolved configuration as TOML text."""
        return dump_toml(self.to_dict())


# --------------------------------------------------------------------------------------------
# loading, overrides, error messages


def _ranges(model: type[BaseModel], field: str) -> str:
    """Human-readable allowed range of a field, from its pydantic metadata."""
    info = model.model_fields.get(field)
    if info is None:
        return ""
    parts = []
    for m in info.metadata:
        for attr, sym in (("gt", ">"), ("ge", "≥"), ("lt", "<"), ("le", "≤")):
            v = getattr(m, attr, None)
            if v is not None:
                parts.append(f"{sym} {v}")
    ann = info.annotation
    args = getattr(ann, "__args__", None)
    if getattr(ann, "__origin__", None) is Literal or (
        args and all(isinstance(a, str) for a in args)
    ):
        parts.append("one of " + ", ".join(repr(a) for a in args))
    return " and ".join(parts)


_SECTIONS: dict[str, type[BaseModel]] = {
    name: f.annotation
    for name, f in Config.model_fields.items()  # type: ignore[misc]
}


def _format_validation_error(err: ValidationError, data: dict[str, Any]) -> str:
    msgs = []
    for e in err.errors():
        loc = [str(p) for p in e["loc"] if not isinstance(p, int)]
        key = ".".join(loc) if loc else "(configuration)"
        value = e.get("input")
        kind = e["type"]
        if kind == "extra_forbidden":
            section = loc[0] if loc else ""
            if len(loc) == 1:
                allowed = ", ".join(_SECTIONS)
                msgs.append(f"unknown section '{key}'; allowed sections: {allowed}")
            else:
                model = _SECTIONS.get(section)
                allowed = ", ".join(model.model_fields) if model else ""
                msgs.append(f"unknown key '{key}'; allowed keys in [{section}]: {allowed}")
            continue
        rng = ""
        if len(loc) == 2 and loc[0] in _SECTIONS:
            rng = _ranges(_SECTIONS[loc[0]], loc[1])
        text = e["msg"]
        if text.startswith("Value error, "):
            text = text[len("Value error, ") :]
            msgs.append(text if key == "(configuration)" or key in text else f"{key}: {text}")
            continue
        msg = f"{key} = {value!r} is invalid: {text}"
        if rng:
            msg += f" (allowed: {rng})"
        msgs.append(msg)
    return "invalid configuration: " + "; ".join(msgs)


def parse_override(item: str) -> tuple[list[str], Any]:
    """Parse one ``section.key=value`` override; the value uses TOML syntax.

    A bare word that is not valid TOML is taken as a string (``--set scenario.kind=chute``).
    """
    if "=" not in item:
        raise ConfigError(
            f"--set {item!r}: expected section.key=value (e.g. --set geometry.slope_deg=24)"
        )
    key, raw = item.split("=", 1)
    key = key.strip()
    parts = key.split(".")
    if len(parts) != 2 or not all(p.strip() for p in parts):
        raise ConfigError(
            f"--set {item!r}: the key {key!r} must have the form section.key "
            f"with a section among {', '.join(_SECTIONS)}"
        )
    raw = raw.strip()
    if raw == "":
        raise ConfigError(f"--set {item!r}: missing value for key {key!r}")
    if "\n" in raw or "\r" in raw:
        raise ConfigError(f"--set {key}: the value must be on one line")
    try:
        value = tomllib.loads(f"v = {raw}")["v"]
    except RecursionError:
        raise ConfigError(f"--set {key}: the value is nested too deeply") from None
    except tomllib.TOMLDecodeError:
        if any(c in raw for c in "[]{}\"'=\n"):
            raise ConfigError(f"--set {item!r}: the value {raw!r} is not valid TOML") from None
        value = raw
    return parts, value


def apply_overrides(data: dict[str, Any], overrides: list[str] | None) -> dict[str, Any]:
    """Apply ``--set`` overrides to raw configuration data (before validation)."""
    data = copy.deepcopy(data)
    for item in overrides or []:
        (section, key), value = parse_override(item)
        if section not in _SECTIONS:
            raise ConfigError(
                f"--set {item!r}: unknown section '{section}'; allowed sections: {', '.join(_SECTIONS)}"
            )
        sec = data.setdefault(section, {})
        if not isinstance(sec, dict):
            raise ConfigError(f"configuration section '{section}' must be a table")
        sec[key] = value
    return data


def validate_data(data: dict[str, Any]) -> Config:
    """Validate raw data into a :class:`Config`, raising :class:`ConfigError` with a clear message."""
    if not isinstance(data, dict):
        raise ConfigError("invalid configuration: the top level must be a table of sections")
    try:
        return Config.model_validate(data)
    except ValidationError as err:
        raise ConfigError(_format_validation_error(err, data)) from None


def read_toml(path: str | Path, what: str = "configuration") -> dict[str, Any]:
    """Read a TOML file into raw data, with errors as :class:`ConfigError` naming the file as
    ``what`` ("configuration", "sweep", "calibration")."""
    p = Path(path)
    if not p.exists():
        raise ConfigError(f"{what} file {str(p)!r} does not exist")
    if not p.is_file():
        raise ConfigError(f"{what} path {str(p)!r} is not a file")
    try:
        with p.open("rb") as fh:
            return tomllib.load(fh)
    except tomllib.TOMLDecodeError as err:
        raise ConfigError(f"{what} file {str(p)!r} is not valid TOML: {err}") from None
    except RecursionError:
        raise ConfigError(f"{what} file {str(p)!r} is nested too deeply") from None
    except (OSError, UnicodeDecodeError) as err:
        raise ConfigError(f"{what} file {str(p)!r} cannot be read: {err}") from None


def preset_names() -> list[str]:
    """The built-in presets a file may ``extends``."""
    from importlib import resources

    return sorted(p.name[:-5] for p in resources.files("segmpm").joinpath("presets").iterdir()
                  if p.name.endswith(".toml"))  # fmt: skip


def preset_data(name: str) -> dict[str, Any]:
    """The raw data of the built-in preset ``name`` (``presets/NAME.toml``)."""
    from importlib import resources

    if name not in preset_names():
        raise ConfigError(
            f"extends = {name!r}: no such preset; allowed: {', '.join(preset_names())} "
            "or the path of a TOML file"
        )
    return tomllib.loads(resources.files("segmpm").joinpath(f"presets/{name}.toml").read_text())


def resolve_extends(data: dict[str, Any], base_dir: Path | None, depth: int = 0) -> dict[str, Any]:
    """Merge a configuration that names a base (top-level ``extends = "PRESET"`` or a path,
    relative to the file) over that base, section by section; a file without ``extends`` is
    returned as it is (resolved onto the schema's defaults)."""
    if "extends" not in data:
        return data
    data = dict(data)
    ext = data.pop("extends")
    if not isinstance(ext, str) or not ext:
        raise ConfigError(f"extends = {ext!r} must be a preset name ({', '.join(preset_names())}) "
                          "or the path of a TOML file")  # fmt: skip
    if depth > 8:
        raise ConfigError(f"extends = {ext!r}: more than 8 levels of extends (a cycle?)")
    if ext in preset_names():
        base = preset_data(ext)
        bdir = None
    else:
        p = Path(ext)
        if not p.is_absolute() and base_dir is not None:
            p = base_dir / p
        if not p.exists() and not ext.endswith(".toml"):
            raise ConfigError(f"extends = {ext!r}: no such preset ({', '.join(preset_names())}) "
                              f"and no file {str(p)!r}")  # fmt: skip
        base = read_toml(p)
        bdir = p.parent
    base = resolve_extends(base, bdir, depth + 1)
    out = copy.deepcopy(base)
    for sec, table in data.items():
        if isinstance(table, dict) and isinstance(out.get(sec), dict):
            out[sec].update(table)
        else:
            out[sec] = table
    return out


def is_preset_name(path: str | Path) -> bool:
    """True when ``path`` names a built-in preset (``chute_seed``) rather than a file: no
    ``.toml`` suffix, no such file, and a preset of that name exists."""
    s = str(path)
    return not s.endswith(".toml") and not Path(s).exists() and s in preset_names()


def load_config(path: str | Path | None = None, overrides: list[str] | None = None, *,
                preset: str | None = None) -> Config:  # fmt: skip
    """Load a configuration and apply overrides: a TOML file (``path``), a built-in preset
    (``preset``, or ``path`` given as a preset name such as ``"chute_seed"``), or, with
    neither, the built-in default (``DEFAULT_PRESET``).

    A file may start from a built-in preset or another file with a top-level
    ``extends = "chute_seed"`` (or a path); its sections then override the base's keys.

    >>> cfg = load_config(overrides=["time.end=0.1"])
    >>> cfg.scenario.kind, cfg.material.rheology
    ('chute', 'nonlocal')
    >>> load_config(preset="chute_seed").material.rheology
    'local'
    """
    if path is not None and preset is not None:
        raise ConfigError("give a configuration file or a preset, not both")
    if path is not None and is_preset_name(path):
        path, preset = None, str(path)
    if path is not None:
        data = resolve_extends(read_toml(path), Path(path).parent)
    elif preset is not None:
        data = resolve_extends(preset_data(preset), None)
    else:
        data = default_data()
    data = apply_overrides(data, overrides)
    return validate_data(data)


#: The preset ``segmpm run`` uses without a configuration: the grain-calibrated nonlocal model of
#: the seed chute (docs/validation.md §3 "The default": it beat the seed's local model on every
#: DEM case). The seed's reduced local model is the preset ``chute_seed``.
DEFAULT_PRESET = "chute_nonlocal"


def default_data() -> dict[str, Any]:
    """The built-in default configuration, ``DEFAULT_PRESET`` with its ``extends`` resolved."""
    return resolve_extends(preset_data(DEFAULT_PRESET), None)


# --------------------------------------------------------------------------------------------
# minimal TOML writer (the configuration is two levels deep: sections of scalars and lists)


_ESCAPES = {"\\": "\\\\", '"': '\\"', "\b": "\\b", "\t": "\\t", "\n": "\\n", "\f": "\\f",
            "\r": "\\r"}  # fmt: skip


def _toml_string(v: str) -> str:
    """A TOML basic string; control characters as escapes so the output always parses."""
    out = []
    for ch in v:
        if ch in _ESCAPES:
            out.append(_ESCAPES[ch])
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append(f"\\u{ord(ch):04X}")
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if math.isnan(v) or math.isinf(v):
            raise ValueError("non-finite value in configuration")
        return repr(v)
    if isinstance(v, str):
        return _toml_string(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dump_toml(data: dict[str, Any]) -> str:
    """Serialise a two-level configuration dictionary to TOML."""
    lines: list[str] = []
    for section, table in data.items():
        lines.append(f"[{section}]")
        for k, v in table.items():
            lines.append(f"{k} = {_toml_value(v)}")
        lines.append("")
    return "\n".join(lines)
