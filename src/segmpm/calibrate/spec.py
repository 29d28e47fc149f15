"""The calibration file ``CAL.toml``: pydantic schema, reading, and the resolved cases.

The format (every key, default and range) is documented in docs/calibrate.md; the schema below is
its source. Errors are :class:`segmpm.config.ConfigError` naming the key, the value and the
allowed range (exit 2).
"""

from __future__ import annotations

import copy
import hashlib
import json
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from ..analysis.compare import CompareError, Reference, read_reference, surface_velocity
from ..config import (
    _SECTIONS,
    Config,
    ConfigError,
    ScenarioConfig,
    apply_overrides,
    preset_data,
    preset_names,
    read_toml,
    resolve_extends,
    validate_data,
)

CAL_KEYS = ("parameters", "cases", "objective", "optimiser", "inner", "sensitivity")
NAME_RE = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,63}$")
PosFloat = Annotated[float, Field(gt=0, allow_inf_nan=False)]
NonNegFloat = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Time = Annotated[float, Field(gt=0, le=1e5, allow_inf_nan=False)]


class _Table(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ParameterSpec(_Table):
    """One fitted configuration key."""

    #: the configuration key in the ``--set`` form, ``section.key``
    key: Annotated[str, Field(min_length=3, max_length=200)]
    #: bounds of the search (inside the key's own range in the schema)
    lower: Annotated[float, Field(allow_inf_nan=False)]
    upper: Annotated[float, Field(allow_inf_nan=False)]
    #: "log" (searched uniformly in ln x; needs lower > 0) or "linear"
    scale: Literal["log", "linear"] = "linear"

    @model_validator(mode="after")
    def _check(self) -> ParameterSpec:
        parts = self.key.split(".")
        if len(parts) != 2 or parts[0] not in _SECTIONS:
            raise ValueError(
                f"key = {self.key!r} must have the form section.key with a section among "
                f"{', '.join(_SECTIONS)}"
            )
        model = _SECTIONS[parts[0]]
        if parts[1] not in model.model_fields:
            raise ValueError(
                f"key = {self.key!r}: no key {parts[1]!r} in [{parts[0]}]; allowed: "
                f"{', '.join(model.model_fields)}"
            )
        if not self.lower < self.upper:
            raise ValueError(
                f"lower = {self.lower} must be smaller than upper = {self.upper} (key {self.key})"
            )
        if self.scale == "log" and self.lower <= 0:
            raise ValueError(
                f"scale = 'log' needs lower > 0; got lower = {self.lower} (key {self.key}); "
                "use scale = 'linear' for a range that includes 0"
            )
        return self


class CaseSpec(_Table):
    """One reference and the configuration that is compared with it."""

    #: label of the case (a file-name-safe word); default case0, case1, …
    name: str | None = None
    #: reference CSV in the format of ``segmpm compare`` (relative to the CAL file)
    reference: Annotated[str, Field(min_length=1)]
    #: base configuration: a preset name (chute_seed, chute_nonlocal, …) or a TOML path
    base: Annotated[str, Field(min_length=1)]
    #: ``--set``-style overrides applied to the base, before the fitted parameters
    set: list[str] = []
    #: times compared, s (default: objective.times)
    times: list[Time] | None = None
    #: weight of each time (default: 1 each; same length as times)
    time_weights: list[NonNegFloat] | None = None
    #: weight of the case in the joint objective
    weight: NonNegFloat = 1.0
    #: added to the reference's y_m before comparing (compare's --y-offset), m
    y_offset: Annotated[float, Field(ge=-10, le=10, allow_inf_nan=False)] = 0.0

    @model_validator(mode="after")
    def _check(self) -> CaseSpec:
        if self.name is not None and not NAME_RE.match(self.name):
            raise ValueError(
                f"name = {self.name!r} must be 1-64 letters, digits, '_', '-' or '.' "
                "(it names the case's run directory)"
            )
        return self


class ObjectiveSpec(_Table):
    """Weights of the two error norms of ``compare`` and the default times."""

    #: weight of φ_s RMS² (phi_rms of compare)
    phi_weight: NonNegFloat = 1.0
    #: weight of (velocity RMS / reference surface speed)² (u_rms_rel of compare)
    velocity_weight: NonNegFloat = 1.0
    #: times compared when a case gives none, s
    times: list[Time] = [1.0]

    @model_validator(mode="after")
    def _check(self) -> ObjectiveSpec:
        if self.phi_weight == 0 and self.velocity_weight == 0:
            raise ValueError("phi_weight = 0 and velocity_weight = 0: at least one must be > 0")
        return self


class OptimiserSpec(_Table):
    """The search."""

    method: Literal["differential_evolution", "lhs_then_local"] = "lhs_then_local"
    #: seed of the Latin hypercube / differential evolution
    seed: Annotated[int, Field(ge=0, le=2**32 - 1)] = 0
    #: differential_evolution: population = popsize × number of parameters (scipy's popsize)
    popsize: Annotated[int, Field(ge=1, le=1000)] = 8
    #: lhs_then_local: number of Latin-hypercube points (0 = 5 × number of parameters)
    samples: Annotated[int, Field(ge=0, le=100_000)] = 0
    #: differential_evolution: generations (scipy's maxiter); local stage: residual evaluations
    #: of scipy.optimize.least_squares (max_nfev)
    max_iterations: Annotated[int, Field(ge=1, le=100_000)] = 30
    #: hard cap on distinct evaluations (the sensitivity batch comes on top)
    max_evaluations: Annotated[int, Field(ge=1, le=1_000_000)] = 200
    #: differential_evolution: scipy's tol; local stage: ftol = xtol = tolerance
    tolerance: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = 1e-6
    #: differential_evolution: refine its best point with the local stage
    polish: bool = False
    #: local stage: finite-difference step of the Jacobian in the scaled [0, 1] coordinates
    fd_step: Annotated[float, Field(gt=0, le=0.25, allow_inf_nan=False)] = 0.01


class InnerSpec(_Table):
    """The model evaluated: ``scenario.solver`` of every evaluated configuration."""

    model: Literal["mpm", "column"] = "mpm"


class SensitivitySpec(_Table):
    """The local sensitivity / uncertainty at the optimum (docs/calibrate.md)."""

    enabled: bool = True
    #: central-difference step in the dimensionless coordinates θ (ln x, or x/|x*|)
    step: Annotated[float, Field(gt=0, le=1, allow_inf_nan=False)] = 0.05
    #: flag when λ_max/λ of JᵀJ exceeds this (condition number of the combination)
    condition_limit: Annotated[float, Field(gt=1, allow_inf_nan=False)] = 1e8
    #: flag a parameter whose relative standard deviation exceeds this
    relative_std_limit: Annotated[float, Field(gt=0, allow_inf_nan=False)] = 1.0


class CalSpec(_Table):
    """A complete calibration file."""

    parameters: Annotated[list[ParameterSpec], Field(min_length=1, max_length=50)]
    cases: Annotated[list[CaseSpec], Field(min_length=1, max_length=100)]
    objective: ObjectiveSpec = ObjectiveSpec()
    optimiser: OptimiserSpec = OptimiserSpec()
    inner: InnerSpec = InnerSpec()
    sensitivity: SensitivitySpec = SensitivitySpec()

    @model_validator(mode="after")
    def _unique(self) -> CalSpec:
        keys = [p.key for p in self.parameters]
        dup = sorted({k for k in keys if keys.count(k) > 1})
        if dup:
            raise ValueError(f"parameters: key(s) {', '.join(dup)} given more than once")
        names = [c.name or f"case{i}" for i, c in enumerate(self.cases)]
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"cases: name(s) {', '.join(dup)} given more than once")
        return self


_MODELS: dict[str, type[BaseModel]] = {
    "parameters": ParameterSpec,
    "cases": CaseSpec,
    "objective": ObjectiveSpec,
    "optimiser": OptimiserSpec,
    "inner": InnerSpec,
    "sensitivity": SensitivitySpec,
}


def _range(model: type[BaseModel] | None, field: str) -> str:
    if model is None or field not in model.model_fields:
        return ""
    info = model.model_fields[field]
    parts = []
    for m in info.metadata:
        for attr, sym in (("gt", ">"), ("ge", "≥"), ("lt", "<"), ("le", "≤")):
            v = getattr(m, attr, None)
            if v is not None:
                parts.append(f"{sym} {v}")
        if getattr(m, "min_length", None):
            parts.append(f"at least {m.min_length} entr(y/ies)")
    args = getattr(info.annotation, "__args__", None)
    if args and all(isinstance(a, str) for a in args):
        parts.append("one of " + ", ".join(repr(a) for a in args))
    return " and ".join(parts)


def _format_error(err: ValidationError, where: str) -> str:
    msgs = []
    for e in err.errors():
        loc = list(e["loc"])
        key = ""
        for p in loc:
            key += f"[{p}]" if isinstance(p, int) else (f".{p}" if key else str(p))
        key = key or "(file)"
        strs = [p for p in loc if isinstance(p, str)]
        model = _MODELS.get(strs[0]) if strs else None
        if e["type"] == "extra_forbidden":
            if len(strs) == 1:
                msgs.append(f"unknown key {key!r}; allowed top-level keys: {', '.join(CAL_KEYS)}")
            else:
                allowed = ", ".join(model.model_fields) if model else ""
                msgs.append(f"unknown key {key!r}; allowed keys there: {allowed}")
            continue
        text = e["msg"]
        if text.startswith("Value error, "):
            msgs.append(f"{key}: {text[len('Value error, ') :]}")
            continue
        rng = _range(model, strs[-1]) if model is not None and len(strs) == 2 else ""
        msg = f"{key} = {e.get('input')!r} is invalid: {text}"
        msgs.append(msg + (f" (allowed: {rng})" if rng else ""))
    return f"{where}: " + "; ".join(msgs)


def read_cal(path: str | Path) -> tuple[CalSpec, dict[str, Any]]:
    """Read and validate ``CAL.toml`` (the schema only; see :func:`resolve`)."""
    p = Path(path)
    where = f"calibration file {str(p)!r}"
    doc = read_toml(p, "calibration")
    try:
        return CalSpec.model_validate(doc), doc
    except ValidationError as err:
        raise ConfigError(_format_error(err, where)) from None


# ---------------------------------------------------------------------------------- resolved


@dataclass
class Parameter:
    """A fitted key with its bounds and the maps between x and the scaled z ∈ [0, 1]."""

    key: str
    lower: float
    upper: float
    scale: str

    def to_x(self, z: float) -> float:
        z = min(1.0, max(0.0, float(z)))
        if self.scale == "log":
            lo, hi = math.log(self.lower), math.log(self.upper)
            return min(self.upper, max(self.lower, math.exp(lo + z * (hi - lo))))
        return min(self.upper, max(self.lower, self.lower + z * (self.upper - self.lower)))

    def to_z(self, x: float) -> float:
        if self.scale == "log":
            lo, hi = math.log(self.lower), math.log(self.upper)
            return (math.log(x) - lo) / (hi - lo)
        return (x - self.lower) / (self.upper - self.lower)


@dataclass
class Case:
    """A resolved case: reference, base configuration data, times and weights."""

    name: str
    reference_path: Path
    reference: Reference
    data: dict[str, Any]
    times: list[float]
    time_weights: list[float]
    weight: float
    y_offset: float
    reference_sha256: str
    #: |surface speed| of the reference at each time (the velocity normalisation)
    u_surface: list[float]

    def config_data(self, values: dict[str, float], solver: str) -> dict[str, Any]:
        """The raw configuration of this case with the fitted ``values`` (before validation)."""
        d = copy.deepcopy(self.data)
        for key, v in values.items():
            sec, name = key.split(".")
            d.setdefault(sec, {})[name] = float(v)
        if solver != "mpm":  # only set when asked: main's scenario.solver defaults to "mpm"
            d.setdefault("scenario", {})["solver"] = solver
        d.setdefault("time", {})["end"] = max(self.times)
        d.setdefault("output", {}).update(
            profile_times=sorted({0.0, *self.times}),
            fields=False,
            figures=False,
            progress=False,
            checkpoint_interval=0.0,
        )
        return d

    def config(self, values: dict[str, float], solver: str) -> Config:
        return validate_data(self.config_data(values, solver))


@dataclass
class Calibration:
    """A validated calibration: parameters, cases, settings, and the file it came from."""

    path: Path
    spec: CalSpec
    parameters: list[Parameter]
    cases: list[Case]

    @property
    def solver(self) -> str:
        return self.spec.inner.model

    def values(self, x: list[float]) -> dict[str, float]:
        return {p.key: float(v) for p, v in zip(self.parameters, x, strict=True)}

    def fingerprint(self) -> dict[str, Any]:
        """What must not change for a calibration to continue in the same OUT (the budget keys
        optimiser.max_evaluations and max_iterations may)."""
        spec = self.spec.model_dump(mode="json")
        for k in ("max_evaluations", "max_iterations"):
            spec["optimiser"].pop(k, None)
        for c, case in zip(spec["cases"], self.cases, strict=True):
            c["name"] = case.name
            c["resolved_base"] = case.data
            c["reference_sha256"] = case.reference_sha256
            c.pop("reference", None)
            c.pop("base", None)
        return spec


def _base_data(base: str, cal_dir: Path) -> dict[str, Any]:
    p = Path(base)
    if not p.is_absolute():
        p = cal_dir / p
    if base in preset_names() and not p.exists():
        return resolve_extends(preset_data(base), None)
    if not p.exists():
        raise ConfigError(
            f"base = {base!r} is neither a preset ({', '.join(preset_names())}) nor a file "
            f"({str(p)!r} does not exist)"
        )
    return resolve_extends(read_toml(p), p.parent)


def resolve_cases(specs: list[CaseSpec], cal_dir: Path, default_times: list[float],
                  parameters: list[Parameter], solver: str, objective: ObjectiveSpec,
                  where: str, prefix: str = "case") -> list[Case]:  # fmt: skip
    """Resolve ``[[cases]]`` (bases, overrides, references) and check every configuration at the
    parameter bounds, raising :class:`ConfigError` naming the case and key."""
    cases = []
    for i, cs in enumerate(specs):
        name = cs.name or f"{prefix}{i}"
        loc = f"{where}: cases[{i}] ({name})"
        try:
            data = apply_overrides(_base_data(cs.base, cal_dir), cs.set)
        except ConfigError as err:
            raise ConfigError(f"{loc}: {err}") from None
        times = list(cs.times) if cs.times is not None else list(default_times)
        if not times:
            raise ConfigError(f"{loc}: times = [] is empty; give at least one time > 0")
        if sorted(set(times)) != times:
            raise ConfigError(f"{loc}: times = {times} must be increasing without repeats")
        tw = list(cs.time_weights) if cs.time_weights is not None else [1.0] * len(times)
        if len(tw) != len(times):
            raise ConfigError(
                f"{loc}: time_weights has {len(tw)} entries, times has {len(times)}; allowed: "
                "the same length"
            )
        ref_path = Path(cs.reference)
        if not ref_path.is_absolute():
            ref_path = cal_dir / ref_path
        try:
            ref = read_reference(ref_path)
        except CompareError as err:
            raise ConfigError(f"{loc}: reference: {err}") from None
        ref_times = ref.times()
        us = []
        for t in times:
            if not ref_times.size or abs(ref_times - t).min() > 1e-6:
                raise ConfigError(
                    f"{loc}: t = {t:g} s is not in the reference {str(ref_path)!r}; allowed: "
                    + ", ".join(f"{v:g}" for v in ref_times)
                )
            y, _, u = ref.at(t)
            speed = abs(surface_velocity(y, u))
            if objective.velocity_weight > 0 and not speed > 1e-12:
                raise ConfigError(
                    f"{loc}: the reference's surface speed at t = {t:g} s is {speed:g} m/s, so "
                    "the velocity error relative to it is undefined; drop that time or set "
                    "objective.velocity_weight = 0"
                )
            us.append(speed)
        case = Case(name, ref_path, ref, data, times, tw, cs.weight, cs.y_offset,
                    hashlib.sha256(ref_path.read_bytes()).hexdigest(), us)  # fmt: skip
        if solver != "mpm" and "solver" not in ScenarioConfig.model_fields:
            raise ConfigError(
                f"{where}: inner.model = {solver!r} sets scenario.solver, which this segmpm does "
                "not have (allowed here: inner.model = 'mpm')"
            )
        for p in parameters:
            for bound in (p.lower, p.upper):
                vals = {q.key: (bound if q is p else q.to_x(0.5)) for q in parameters}
                try:
                    case.config(vals, solver)
                except ConfigError as err:
                    raise ConfigError(
                        f"{loc}: with {p.key} = {bound!r} (a bound of parameters.{p.key}): {err}"
                    ) from None
        cases.append(case)
    return cases


def load_calibration(path: str | Path) -> Calibration:
    """Read, validate and resolve ``CAL.toml`` (raises :class:`ConfigError`)."""
    p = Path(path)
    spec, _ = read_cal(p)
    where = f"calibration file {str(p)!r}"
    params = [Parameter(q.key, q.lower, q.upper, q.scale) for q in spec.parameters]
    cases = resolve_cases(spec.cases, p.parent, spec.objective.times, params, spec.inner.model,
                          spec.objective, where)  # fmt: skip
    return Calibration(p.resolve(), spec, params, cases)


def fingerprint_text(fp: dict[str, Any]) -> str:
    return json.dumps(fp, sort_keys=True, default=str)
