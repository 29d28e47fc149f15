"""``segmpm calibrate CAL.toml`` and ``segmpm predict CAL_OUT``: fitting configuration keys to
reference profiles with the ``compare`` metric, on dask.distributed (docs/calibrate.md).

* :mod:`.spec` — the CAL.toml schema and its resolution (cases, bounds, references);
* :mod:`.evaluate` — one evaluation: ordinary runs and the compare norms, the objective;
* :mod:`.core` — the persisted, resumable evaluator and the optimisers;
* :mod:`.sensitivity` — Gauss–Newton uncertainty and identifiability flags at the optimum;
* :mod:`.outputs` — history.nc, best.json/best.toml, figures.
"""

from __future__ import annotations

import contextlib
import json
import math
import signal
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from ..config import ConfigError
from ..io.atomic import write_json, write_text
from .core import OPTIMISERS, BudgetExhausted, Evaluator, Record, best_record
from .evaluate import PENALTY, _clean
from .outputs import plot_objective, plot_profiles, write_best, write_history
from .sensitivity import run_sensitivity
from .spec import (
    Calibration,
    CalSpec,
    CaseSpec,
    ObjectiveSpec,
    Parameter,
    fingerprint_text,
    load_calibration,
    resolve_cases,
)

__all__ = ["run_calibration", "run_calibrate", "run_predict", "predict", "load_calibration",
           "PENALTY"]  # fmt: skip

EXIT_OK, EXIT_INVALID, EXIT_FAILED, EXIT_INTERRUPTED = 0, 2, 3, 130
MANIFEST = "calibration.json"


def _differences(a: Any, b: Any, prefix: str = "") -> list[str]:
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for k in sorted(set(a) | set(b), key=str):
            out += _differences(a.get(k), b.get(k), f"{prefix}.{k}" if prefix else str(k))
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        out = []
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            out += _differences(x, y, f"{prefix}[{i}]")
        return out
    return [] if a == b else [prefix or "(root)"]


def _check_manifest(cal: Calibration, out: Path) -> None:
    """Refuse to continue a calibration of a different CAL in OUT (exit 2, naming the keys)."""
    path = out / MANIFEST
    fp = cal.fingerprint()
    if path.exists():
        try:
            old = json.loads(path.read_text())["fingerprint"]
        except (OSError, ValueError, KeyError) as err:
            raise ConfigError(f"--out {str(out)!r}: {path.name} cannot be read ({err}); use "
                              "another --out") from None  # fmt: skip
        if fingerprint_text(old) != fingerprint_text(json.loads(fingerprint_text(fp))):
            diff = _differences(old, json.loads(fingerprint_text(fp)))
            raise ConfigError(
                f"--out {str(out)!r} holds a calibration of another CAL file: it differs in "
                f"{', '.join(diff[:8])}{' …' if len(diff) > 8 else ''}; only "
                "optimiser.max_evaluations and optimiser.max_iterations may change when a "
                "calibration continues; use another --out"
            )
    cases = [{"name": c.name, "reference": str(c.reference_path), "data": c.data,
              "times": c.times, "time_weights": c.time_weights, "weight": c.weight,
              "y_offset": c.y_offset} for c in cal.cases]  # fmt: skip
    write_json(path, {"calibration": str(cal.path), "spec": cal.spec.model_dump(mode="json"),
                      "cases": cases, "fingerprint": json.loads(fingerprint_text(fp))})  # fmt: skip


def _format_flags(sens: dict[str, Any]) -> list[str]:
    lines = []
    for nm in sens.get("parameters", []):
        rs = sens.get("relative_std", {}).get(nm)
        sd = sens.get("std", {}).get(nm)
        lines.append(f"  {nm}: std {sd:.3g} (relative {rs:.3g})" if rs is not None
                     and sd is not None and math.isfinite(rs) else f"  {nm}: std undetermined")  # fmt: skip
    for f in sens.get("flags", []):
        lines.append(f"  FLAG {f['kind']}: {f['message']}")
    if sens.get("unidentifiable"):
        lines.append("  not identifiable from these data: " + ", ".join(sens["unidentifiable"]))
    else:
        lines.append("  every parameter is identified (no flag)")
    return lines


def run_calibration(cal_path: str | Path, out: str | Path = "calibrate-out",
                    scheduler: str | None = None, workers: int = 0, *,
                    stop_after: int | None = None,
                    on_batch: Callable[[Any, list[Any]], None] | None = None) -> int:  # fmt: skip
    """Run (or continue) a calibration; returns the exit code (0, 3 none completed, 130).

    ``stop_after``: stop as if interrupted after this many new evaluations (tests, smoke runs).
    ``on_batch(client, futures)`` is called after each batch is submitted. Raises
    :class:`ConfigError` on invalid input."""
    from ..io.outdir import OutLock, prepare_out_dir

    cal = load_calibration(cal_path)
    out = Path(out)
    prepare_out_dir(out)
    with OutLock(out):
        _check_manifest(cal, out)
        ev = Evaluator(cal, out, scheduler, workers, stop_after=stop_after)
        ev.on_batch = on_batch
        ev.after_batch = lambda: write_history(cal, ev.records(), out)
        n_old = len(ev.disk)
        print(f"segmpm calibrate: {len(cal.parameters)} parameter(s), {len(cal.cases)} case(s), "
              f"{cal.spec.optimiser.method}, inner model {cal.solver}; {n_old} evaluation(s) "
              f"already in {out / 'evals'}", file=sys.stderr)  # fmt: skip
        note = ""
        try:
            try:
                OPTIMISERS[cal.spec.optimiser.method](ev)
            except BudgetExhausted:
                note = f"optimiser.max_evaluations = {cal.spec.optimiser.max_evaluations} reached"
            best = best_record(list(ev.session.values()))
            sens = None
            if best is not None and cal.spec.sensitivity.enabled:
                sens = run_sensitivity(ev, best)
        except KeyboardInterrupt:
            write_history(cal, ev.records(), out)
            print(f"segmpm calibrate: interrupted after {ev.n_new} new evaluation(s); "
                  f"{len(ev.records())} are in {out / 'evals'}; re-run the same command to "
                  "continue", file=sys.stderr)  # fmt: skip
            return EXIT_INTERRUPTED
        finally:
            ev.close()
        records = ev.records()
        write_history(cal, records, out)
        plot_objective(records, out)
        n_fail = sum(r.status != "completed" for r in ev.session.values())
        summary = {"evaluations": len(ev.session), "new": ev.n_new, "reused": ev.n_reused,
                   "failed": n_fail, "stopped": note or "optimiser converged or finished"}  # fmt: skip
        if best is None:
            write_json(out / "best.json", {"status": "failed", "objective": None, **summary})
            print("segmpm calibrate: no evaluation completed; see history.nc (status, message)",
                  file=sys.stderr)  # fmt: skip
            return EXIT_FAILED
        write_best(cal, best, out, {"summary": summary,
                                    "sensitivity": "sensitivity.json" if sens else None})  # fmt: skip
        dirs = {c.name: out / "evals" / f"{best.index:05d}" / c.name for c in cal.cases}
        plot_profiles(cal, dirs, out)
        if sens is not None:
            write_json(out / "sensitivity.json", _clean(sens))
    print(f"segmpm calibrate: {summary['evaluations']} evaluation(s) ({ev.n_new} new, "
          f"{ev.n_reused} reused, {n_fail} failed); {summary['stopped']}", file=sys.stderr)  # fmt: skip
    print(f"best (evaluation {best.index:05d}): objective {best.objective:.6g}")
    for k, v in cal.values(best.x).items():
        print(f"  {k} = {v:.6g}")
    for pc in best.cases:
        for t in pc["terms"]:
            sk = t.get("segregation_skill")
            print(f"  {pc['case']} t = {t['time']:g} s: rms dphi {t['phi_rms']:.4f}, rms du/us "
                  f"{(t['u_rms_rel'] or math.nan):.4f}, skill "
                  f"{sk if sk is None else round(sk, 3)}")  # fmt: skip
    if sens is not None:
        print("sensitivity (sensitivity.json):")
        print("\n".join(_format_flags(sens)))
    print(
        f"wrote {out}/best.json, best.toml, history.nc, objective.png, profiles.png"
        + (", sensitivity.json" if sens else "")
    )
    return EXIT_OK


def run_calibrate(cal_path: str, out: str = "calibrate-out", scheduler: str | None = None,
                  workers: int = 0, predict_cases: str | None = None) -> int:  # fmt: skip
    """CLI entry point of ``segmpm calibrate``."""
    if workers is not None and workers < 0:
        print(f"segmpm: error: --workers = {workers} must be ≥ 0 (0 = default, 2)", file=sys.stderr)
        return EXIT_INVALID
    if predict_cases is not None and not Path(predict_cases).is_file():
        print(f"segmpm: error: --predict {predict_cases!r}: no such file", file=sys.stderr)
        return EXIT_INVALID
    with _sigterm_interrupts():
        code = run_calibration(cal_path, out, scheduler, workers)
    if code != EXIT_OK or predict_cases is None:
        return code
    return run_predict(out, predict_cases, None, scheduler, workers)


@contextlib.contextmanager
def _sigterm_interrupts() -> Iterator[None]:
    """SIGTERM (a batch system's preemption) stops like Ctrl-C: the history is written and the
    exit code is 130; the same command continues later."""

    def handler(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    try:
        old = signal.signal(signal.SIGTERM, handler)
    except ValueError:  # not the main thread
        yield
        return
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, old)


# ---------------------------------------------------------------------------------- predict


def _load_fit(cal_out: Path) -> tuple[Calibration, dict[str, Any]]:
    man, best_p = cal_out / MANIFEST, cal_out / "best.json"
    if not man.is_file() or not best_p.is_file():
        raise ConfigError(f"{str(cal_out)!r} is not the output of a completed segmpm calibrate "
                          f"(no {man.name} or {best_p.name})")  # fmt: skip
    m = json.loads(man.read_text())
    best = json.loads(best_p.read_text())
    if best.get("status") != "completed":
        raise ConfigError(f"{str(best_p)!r}: the calibration has no completed best point")
    spec = CalSpec.model_validate(m["spec"])
    params = [Parameter(q.key, q.lower, q.upper, q.scale) for q in spec.parameters]
    cal = Calibration(Path(m["calibration"]), spec, params, [])
    return cal, best


def predict(cal_out: str | Path, heldout: str | Path | None = None, out: str | Path | None = None,
            scheduler: str | None = None, workers: int = 0) -> dict[str, Any]:  # fmt: skip
    """Run the calibrated parameters on held-out cases and write ``crossval.json`` and
    ``crossval.md`` (raises :class:`ConfigError`)."""
    from pydantic import BaseModel, ConfigDict, ValidationError

    from .spec import _format_error

    cal_out = Path(cal_out)
    cal, best = _load_fit(cal_out)
    out = Path(out) if out is not None else cal_out / "predict"
    rows: list[dict[str, Any]] = []
    for pc in best["per_case"]:
        for t in pc["terms"]:
            rows.append({"set": "fit", "case": pc["case"], **t})
    held: list[Any] = []
    rec: Record | None = None
    if heldout is not None:

        class HeldOut(BaseModel):
            model_config = ConfigDict(extra="forbid")
            cases: list[CaseSpec]
            objective: ObjectiveSpec | None = None

        import tomllib

        hp = Path(heldout)
        where = f"held-out cases file {str(hp)!r}"
        try:
            doc = tomllib.loads(hp.read_text())
            spec = HeldOut.model_validate(doc)
        except (OSError, UnicodeDecodeError) as err:
            raise ConfigError(f"{where} cannot be read: {err}") from None
        except tomllib.TOMLDecodeError as err:
            raise ConfigError(f"{where} is not valid TOML: {err}") from None
        except ValidationError as err:
            raise ConfigError(_format_error(err, where)) from None
        objective = spec.objective or cal.spec.objective
        held = resolve_cases(spec.cases, hp.parent, objective.times, cal.parameters,
                             cal.solver, cal.spec.objective, where, prefix="heldout")  # fmt: skip
        pcal = Calibration(hp.resolve(), cal.spec, cal.parameters, held)
        from ..io.outdir import OutLock, prepare_out_dir

        prepare_out_dir(out)
        with OutLock(out):
            ev = Evaluator(pcal, out, scheduler, workers)
            try:
                x = [float(best["parameters"][p.key]) for p in cal.parameters]
                rec = ev.evaluate([x], "predict", budget=False)[0]
            finally:
                ev.close()
        for c, pc in zip(held, rec.cases, strict=True):
            if pc.get("status") != "completed":
                rows.append({"set": "held-out", "case": c.name, "time": None,
                             "status": pc.get("status")})  # fmt: skip
            for t in pc.get("terms", []):
                rows.append({"set": "held-out", "case": c.name, **t})
        plot_profiles(pcal, {c.name: out / "evals" / f"{rec.index:05d}" / c.name for c in held},
                      out, "profiles_heldout.png")  # fmt: skip
    else:
        out.mkdir(parents=True, exist_ok=True)
    data = {"calibration": str(cal_out.resolve()), "parameters": best["parameters"],
            "heldout": str(Path(heldout).resolve()) if heldout else None,
            "columns": {"phi_rms": "rms Δφ_s over the whole reference depth (compare)",
                        "u_rms_rel": "rms Δu / |u_s of the reference|",
                        "segregation_skill": "1 − phi_rms / rms(φ_s,ref − φ₀)"},
            "rows": rows}  # fmt: skip
    write_json(out / "crossval.json", _clean(data))
    write_text(out / "crossval.md", crossval_table(rows, best["parameters"]))
    return data


def crossval_table(rows: list[dict[str, Any]], params: dict[str, float]) -> str:
    """The Markdown cross-validation table."""

    def f(v: Any, fmt: str) -> str:
        return format(v, fmt) if isinstance(v, int | float) and math.isfinite(v) else "n/a"

    lines = ["# Cross-validation of the calibrated parameters", "",
             ", ".join(f"`{k}` = {v:.6g}" for k, v in params.items()), "",
             "| set | case | t (s) | rms Δφ_s | rms Δu / u_s | skill | u_s run / ref (m/s) |",
             "|---|---|---|---|---|---|---|"]  # fmt: skip
    for r in rows:
        if r.get("time") is None:
            lines.append(f"| {r['set']} | {r['case']} | {r.get('status', 'failed')} | | | | |")
            continue
        lines.append(f"| {r['set']} | {r['case']} | {r['time']:g} | {f(r.get('phi_rms'), '.4f')} "
                     f"| {f(r.get('u_rms_rel'), '.4f')} | {f(r.get('segregation_skill'), '.3f')} "
                     f"| {f(r.get('u_surface_run'), '.4g')} / "
                     f"{f(r.get('u_surface_reference'), '.4g')} |")  # fmt: skip
    return "\n".join(lines) + "\n"


def run_predict(cal_out: str | Path, heldout: str | None = None, out: str | None = None,
                scheduler: str | None = None, workers: int = 0) -> int:  # fmt: skip
    """CLI entry point of ``segmpm predict``."""
    try:
        with _sigterm_interrupts():
            data = predict(cal_out, heldout, out, scheduler, workers)
    except KeyboardInterrupt:
        print("segmpm predict: interrupted; re-run the same command to continue", file=sys.stderr)
        return EXIT_INTERRUPTED
    except ConfigError as err:
        print(f"segmpm: error: {err}", file=sys.stderr)
        return EXIT_INVALID
    dest = Path(out) if out else Path(cal_out) / "predict"
    print(crossval_table(data["rows"], data["parameters"]))
    print(f"wrote {dest / 'crossval.json'} and {dest / 'crossval.md'}")
    bad = [r for r in data["rows"] if r.get("time") is None]
    return EXIT_FAILED if bad else EXIT_OK
