"""One evaluation: ordinary runs of the resolved configurations, then the ``compare`` metric.

:func:`run_case` is the dask task (one case of one evaluation). It runs the configuration with
:func:`segmpm.sweep.run_member` (the run path of ``segmpm sweep``: one numba thread, the folder's
lock, ``run.json``/``profiles.nc``) into ``OUT/evals/NNNNN/CASE``, computes the norms of
:func:`segmpm.analysis.compare.compare_time` at the case's times over the whole reference depth,
and writes ``result.json`` there atomically before it returns: a task that dask runs again (its
worker died after the task finished) finds it and returns it without running again.
"""

from __future__ import annotations

import json
import math
import time as _time
from pathlib import Path
from typing import Any

import numpy as np

from ..analysis.compare import (
    TIME_TOL,
    compare_time,
    interpolate_defined,
    read_reference,
    read_run,
)
from ..io.atomic import write_json

#: objective of a failed evaluation (a numerical failure, an invalid run, a non-finite metric).
PENALTY = 1.0e6
RESULT = "result.json"
TERM_KEYS = ("phi_rms", "u_rms_rel", "segregation_skill", "u_surface_run", "u_surface_reference")


def _clean(v: Any) -> Any:
    if isinstance(v, float | np.floating):
        v = float(v)
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {k: _clean(x) for k, x in v.items()}
    if isinstance(v, list | tuple | np.ndarray):
        return [_clean(x) for x in v]
    if isinstance(v, np.integer):
        return int(v)
    return v


def case_metrics(out_dir: str | Path, reference: str | Path, times: list[float],
                 y_offset: float) -> dict[str, Any]:  # fmt: skip
    """The compare norms at ``times`` and the per-bin residuals (Δφ_s, Δu/|u_s,ref|) behind them.

    The residuals are those of :func:`compare_time`: the run interpolated at every reference row
    with a value, over the whole depth (:func:`interpolate_defined`), so that
    ``sqrt(mean(dphi**2)) == phi_rms`` and ``sqrt(mean(du**2)) == u_rms_rel``. Raises ValueError
    when the run lacks a time or has no material at one."""
    run = read_run(out_dir)
    ref = read_reference(reference)
    terms = []
    for t in times:
        i = run.index(t)
        if abs(run.time[i] - t) > TIME_TOL:
            raise ValueError(f"the run has no profile at t = {t:g} s")
        m = compare_time(run, ref, t, y_offset)
        y_ref, phi_ref, u_ref = ref.at(t)
        y_ref = y_ref + y_offset
        _, phi_run, phi_r, _ = interpolate_defined(run.y, run.phi[i], y_ref, phi_ref)
        _, u_run, u_r, _ = interpolate_defined(run.y, run.u[i], y_ref, u_ref)
        n_phi = int(np.isfinite(phi_ref).sum())
        n_u = int(np.isfinite(u_ref).sum())
        if phi_run.size != n_phi or u_run.size != n_u:
            raise ValueError(f"the run has no material at t = {t:g} s")
        us = abs(m["u_surface_reference"])
        terms.append({**{k: m[k] for k in TERM_KEYS}, "time": float(t),
                      "dphi": (phi_run - phi_r).tolist(),
                      "du": ((u_run - u_r) / us).tolist() if us > 1e-12 else []})  # fmt: skip
    return {"terms": terms}


def run_case(config: dict[str, Any], run_dir: str, reference: str, times: list[float],
             y_offset: float, tag: dict[str, Any]) -> dict[str, Any]:  # fmt: skip
    """The dask task: run one case of one evaluation and measure it (see the module docstring).

    ``tag`` (the evaluation's parameter vector and the configuration's hash) is stored in
    ``result.json``; an existing ``result.json`` with the same tag is returned as it is."""
    d = Path(run_dir)
    res_path = d / RESULT
    try:
        old = json.loads(res_path.read_text())
        if old.get("tag") == tag:
            return old
    except (OSError, ValueError):
        pass
    from ..sweep import run_member

    t0 = _time.perf_counter()
    d.mkdir(parents=True, exist_ok=True)
    r = run_member(config, str(d), False)
    out: dict[str, Any] = {"tag": tag, "status": r.get("status", "failed"),
                           "exit_code": r.get("exit_code"), "message": r.get("message", "")}  # fmt: skip
    if out["status"] == "completed":
        try:
            out.update(case_metrics(d, reference, times, y_offset))
            bad = [t["time"] for t in out["terms"]
                   if not all(math.isfinite(v) for v in (*t["dphi"], *t["du"]))
                   or not math.isfinite(t["phi_rms"])]  # fmt: skip
            if bad:
                raise ValueError(
                    "non-finite metric at t = " + ", ".join(f"{v:g}" for v in bad) + " s"
                )
        except Exception as err:  # noqa: BLE001 - a metric that cannot be computed fails it
            out.update(status="failed", exit_code=None, message=f"metric: {err}", terms=[])
    out["wall_time_s"] = _time.perf_counter() - t0
    out = _clean(out)
    write_json(res_path, out)
    return out


def combine(case_results: list[dict[str, Any]], cases: list[Any], phi_w: float,
            u_w: float) -> dict[str, Any]:  # fmt: skip
    """The objective of one evaluation from its cases' results.

    J = (1/W) Σ_c w_c Σ_t w_t (w_φ φ_rms² + w_u (u_rms/u_s)²), W = Σ_c w_c Σ_t w_t, and the
    residual vector r (per reference bin, scaled so that rᵀr = J). A failed case gives
    J = PENALTY."""
    total_w = sum(c.weight * sum(c.time_weights) for c in cases) or 1.0
    per_case, resid, status, msgs = [], [], "completed", []
    j = 0.0
    for c, r in zip(cases, case_results, strict=True):
        if r.get("status") != "completed":
            status = "failed"
            msgs.append(f"{c.name}: {r.get('status')}: {r.get('message', '')}".strip())
            per_case.append({"case": c.name, "objective": None, "status": r.get("status"),
                             "terms": []})  # fmt: skip
            continue
        jc = 0.0
        for t, wt in zip(r["terms"], c.time_weights, strict=True):
            w = c.weight * wt / total_w
            u2 = t["u_rms_rel"] ** 2 if t["u_rms_rel"] is not None else 0.0
            jc += w * (phi_w * t["phi_rms"] ** 2 + (u_w * u2 if u_w > 0 else 0.0))
            if phi_w > 0 and t["dphi"]:
                s = math.sqrt(w * phi_w / len(t["dphi"]))
                resid.extend(s * v for v in t["dphi"])
            if u_w > 0 and t["du"]:
                s = math.sqrt(w * u_w / len(t["du"]))
                resid.extend(s * v for v in t["du"])
        j += jc
        per_case.append({"case": c.name, "objective": jc, "status": "completed",
                         "terms": [{k: t[k] for k in ("time", *TERM_KEYS)}
                                   for t in r["terms"]]})  # fmt: skip
    if status != "completed" or not math.isfinite(j):
        if status == "completed":
            msgs.append("non-finite objective")
        status, j, resid = "failed", PENALTY, []
    return {"objective": j, "status": status, "message": "; ".join(msgs), "cases": per_case,
            "residuals": resid}  # fmt: skip
