"""Outputs of a calibration: history.nc, best.json/best.toml, objective.png, profiles.png."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from .. import __version__
from ..config import dump_toml
from ..io.atomic import write_json, write_text, write_with
from .core import Record
from .evaluate import _clean
from .spec import Calibration


def _terms(cal: Calibration) -> list[tuple[str, float]]:
    return [(c.name, t) for c in cal.cases for t in c.times]


def write_history(cal: Calibration, records: list[Record], out: Path) -> Path:
    """``history.nc``: one entry per evaluation along ``evaluation`` (see docs/calibrate.md)."""
    import xarray as xr

    names = [p.key for p in cal.parameters]
    terms = _terms(cal)
    ne, nt = len(records), len(terms)
    arr = {k: np.full((ne, nt), np.nan) for k in ("phi_rms", "u_rms_rel", "segregation_skill",
                                                   "u_surface_run")}  # fmt: skip
    case_obj = np.full((ne, len(cal.cases)), np.nan)
    pos = {tc: i for i, tc in enumerate(terms)}
    cidx = {c.name: i for i, c in enumerate(cal.cases)}
    for e, r in enumerate(records):
        for pc in r.cases:
            if pc.get("objective") is not None and pc["case"] in cidx:
                case_obj[e, cidx[pc["case"]]] = pc["objective"]
            for t in pc.get("terms", []):
                i = pos.get((pc["case"], t["time"]))
                if i is None:
                    continue
                for k in arr:
                    v = t.get(k)
                    arr[k][e, i] = v if v is not None else np.nan
    x = np.asarray([r.x for r in records], dtype=float).reshape(ne, len(names))
    z = np.asarray([[p.to_z(v) for p, v in zip(cal.parameters, r.x, strict=True)]
                    for r in records], dtype=float).reshape(ne, len(names))  # fmt: skip
    obj = np.asarray([r.objective for r in records], dtype=float)
    best_so_far = np.full(ne, np.nan)
    b = math.inf
    for e, r in enumerate(records):
        if r.status == "completed" and r.stage != "sensitivity":
            b = min(b, r.objective)
        best_so_far[e] = b if math.isfinite(b) else np.nan
    ds = xr.Dataset(
        {
            "x": (("evaluation", "parameter"), x, {"long_name": "parameter values"}),
            "z": (("evaluation", "parameter"), z, {"long_name": "scaled coordinates in [0, 1]"}),
            "objective": ("evaluation", obj, {"long_name": "objective J (docs/calibrate.md)"}),
            "best_so_far": ("evaluation", best_so_far),
            "case_objective": (("evaluation", "case"), case_obj),
            "phi_rms": (("evaluation", "term"), arr["phi_rms"]),
            "u_rms_rel": (
                ("evaluation", "term"),
                arr["u_rms_rel"],
                {"long_name": "velocity RMS / reference surface speed"},
            ),  # fmt: skip
            "segregation_skill": (("evaluation", "term"), arr["segregation_skill"]),
            "u_surface_run": (("evaluation", "term"), arr["u_surface_run"], {"units": "m/s"}),
            "status": ("evaluation", np.asarray([r.status for r in records], dtype=str)),
            "stage": ("evaluation", np.asarray([r.stage for r in records], dtype=str)),
            "message": ("evaluation", np.asarray([r.message for r in records], dtype=str)),
            "wall_time_s": ("evaluation", np.asarray([r.wall_time_s for r in records], float)),
        },
        coords={
            "evaluation": np.asarray([r.index for r in records], dtype=int),
            "parameter": np.asarray(names, dtype=str),
            "case": np.asarray([c.name for c in cal.cases], dtype=str),
            "term_case": ("term", np.asarray([t[0] for t in terms], dtype=str)),
            "term_time": ("term", np.asarray([t[1] for t in terms], dtype=float)),
        },
        attrs={
            "title": "segmpm calibration history",
            "segmpm_version": __version__,
            "calibration": str(cal.path),
            "scales": ", ".join(p.scale for p in cal.parameters),
            "method": cal.spec.optimiser.method,
            "inner_model": cal.solver,
        },  # fmt: skip
    )
    path = out / "history.nc"
    write_with(path, lambda tmp: ds.to_netcdf(tmp, engine="h5netcdf"))
    return path


def write_best(cal: Calibration, best: Record, out: Path, extra: dict[str, Any]) -> None:
    """``best.json`` and the resolved configurations ``best.toml`` (first case) and
    ``best-CASE.toml`` (every case)."""
    vals = cal.values(best.x)
    data = {"parameters": vals, "objective": best.objective, "evaluation": best.index,
            "status": best.status, "per_case": best.cases, **extra}  # fmt: skip
    write_json(out / "best.json", _clean(data))
    for i, c in enumerate(cal.cases):
        cfg = c.config(vals, cal.solver)
        head = (f"# segmpm calibrate: best point (evaluation {best.index:05d}, objective "
                f"{best.objective:.6g}) for case {c.name!r}\n# fitted: "
                + ", ".join(f"{k} = {v!r}" for k, v in vals.items()) + "\n")  # fmt: skip
        text = head + dump_toml(cfg.to_dict())
        write_text(out / f"best-{c.name}.toml", text)
        if i == 0:
            write_text(out / "best.toml", text)


def plot_objective(records: list[Record], out: Path) -> Path:
    """``objective.png``: the objective of every evaluation and the best so far."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.0))
    idx = np.asarray([r.index for r in records])
    ok = np.asarray([r.status == "completed" for r in records])
    obj = np.asarray([r.objective for r in records], dtype=float)
    if ok.any():
        ax.semilogy(idx[ok], obj[ok], "o", ms=3.5, color="C0", label="evaluation")
        best, b = [], math.inf
        for r in records:
            if r.status == "completed" and r.stage != "sensitivity":
                b = min(b, r.objective)
            best.append(b if math.isfinite(b) else np.nan)
        ax.semilogy(idx, best, "-", color="C3", lw=1.5, label="best so far")
    if (~ok).any():
        lo = np.nanmin(obj[ok]) if ok.any() else 1.0
        ax.plot(idx[~ok], np.full((~ok).sum(), lo), "x", color="k", label="failed (penalised)")
    ax.set_xlabel("evaluation")
    ax.set_ylabel("objective J")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    path = out / "objective.png"
    write_with(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))
    plt.close(fig)
    return path


def plot_profiles(cal: Calibration, run_dirs: dict[str, Path], out: Path,
                  name: str = "profiles.png", cases: list[Any] | None = None) -> Path:  # fmt: skip
    """``profiles.png``: per case two rows (φ_s, u) and one column per time, the best fit (lines)
    against the reference (circles)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..analysis.compare import CompareError, read_run

    cases = cases if cases is not None else cal.cases
    ncol = max(len(c.times) for c in cases)
    fig, axes = plt.subplots(2 * len(cases), ncol, figsize=(3.0 * ncol + 0.6, 3.2 * 2 * len(cases)),
                             squeeze=False)  # fmt: skip
    for ci, c in enumerate(cases):
        try:
            run = read_run(run_dirs[c.name])
        except (CompareError, KeyError):
            run = None
        for j in range(ncol):
            for row in range(2):
                ax = axes[2 * ci + row, j]
                if j >= len(c.times):
                    ax.axis("off")
                    continue
                t = c.times[j]
                y_ref, phi_ref, u_ref = c.reference.at(t)
                vals_ref = phi_ref if row == 0 else u_ref
                ax.plot(vals_ref, (y_ref + c.y_offset) * 1e3, "o", mfc="none", mec="k", ms=4,
                        label="reference")  # fmt: skip
                if run is not None:
                    i = run.index(t)
                    v = run.phi[i] if row == 0 else run.u[i]
                    ok = np.isfinite(v)
                    ax.plot(v[ok], run.y[ok] * 1e3, "-", color="C0", lw=1.6, label="best fit")
                ax.set_xlabel("φ_s" if row == 0 else "u (m/s)")
                ax.grid(alpha=0.3)
                if j == 0:
                    ax.set_ylabel(f"{c.name}\ny (mm)")
                if row == 0:
                    ax.set_title(f"{c.name}, t = {t:g} s", fontsize=9)
    axes[0, 0].legend(fontsize=7)
    fig.tight_layout()
    path = out / name
    write_with(path, lambda tmp: fig.savefig(tmp, dpi=100, format="png"))
    plt.close(fig)
    return path
