"""The evaluator (batches on dask.distributed, persisted and resumable) and the optimisers."""

from __future__ import annotations

import contextlib
import hashlib
import inspect
import json
import math
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..config import ConfigError
from ..io.atomic import write_json
from .evaluate import PENALTY, combine, run_case
from .spec import Calibration

EVAL_FILE = "eval.json"


class BudgetExhausted(Exception):
    """optimiser.max_evaluations distinct evaluations have been made."""


@dataclass
class Record:
    """One evaluation (a parameter vector) and its outcome."""

    index: int
    x: list[float]
    stage: str
    status: str = "pending"
    objective: float = math.nan
    message: str = ""
    cases: list[dict[str, Any]] = field(default_factory=list)
    residuals: list[float] = field(default_factory=list)
    wall_time_s: float = 0.0
    config_sha256: dict[str, str] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"index": self.index, "x": self.x, "stage": self.stage, "status": self.status,
                "objective": self.objective, "message": self.message, "cases": self.cases,
                "residuals": self.residuals, "wall_time_s": self.wall_time_s,
                "config_sha256": self.config_sha256}  # fmt: skip

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> Record:
        return cls(int(d["index"]), [float(v) for v in d["x"]], d["stage"], d["status"],
                   float(d["objective"]), d.get("message", ""), d.get("cases", []),
                   [float(v) for v in d.get("residuals", [])], float(d.get("wall_time_s", 0.0)),
                   d.get("config_sha256", {}))  # fmt: skip


def _sha(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()


class Evaluator:
    """Evaluates batches of parameter vectors, reusing the evaluations found in ``OUT/evals``.

    The k-th distinct vector requested gets the index k (``OUT/evals/{k:05d}``), whatever the
    order in which the workers finish, so a seeded calibration always has the same history (were
    a continued calibration to take another path, e.g. on a machine whose runs differ in the last
    bit, its new vectors get free indices after the known ones: nothing on disk is replaced). An
    evaluation is written (``eval.json``, atomically) as soon as its cases have finished; a
    vector found there with the same configurations is not run again."""

    def __init__(self, cal: Calibration, out: Path, scheduler: str | None, workers: int,
                 stop_after: int | None = None, first_batch: int = 2) -> None:  # fmt: skip
        self.cal, self.out = cal, out
        self.scheduler, self.workers = scheduler, workers
        self.stop_after = stop_after
        self.first_batch = first_batch
        self.disk: dict[tuple[float, ...], Record] = {}
        self.session: dict[tuple[float, ...], Record] = {}
        self.order: list[tuple[float, ...]] = []
        self.n_budget = 0
        self.n_new = 0
        self.n_reused = 0
        self._stack = contextlib.ExitStack()
        self._client = None
        self.on_batch = None  # test hook: called with (client, futures) after each submission
        self.after_batch = None  # called after each batch (history.nc is rewritten there)
        self._load()

    # ------------------------------------------------------------------ disk
    def _load(self) -> None:
        d = self.out / "evals"
        if not d.is_dir():
            return
        for f in sorted(d.glob(f"*/{EVAL_FILE}")):
            try:
                rec = Record.from_json(json.loads(f.read_text()))
            except (OSError, ValueError, KeyError, TypeError):
                continue  # a damaged record is evaluated again
            if rec.status in ("completed", "failed") and rec.config_sha256 == self._hashes(rec.x):
                self.disk[tuple(rec.x)] = rec

    def _configs(self, x: list[float]) -> dict[str, dict[str, Any]]:
        vals = self.cal.values(x)
        return {c.name: c.config(vals, self.cal.solver).to_dict() for c in self.cal.cases}

    def _hashes(self, x: list[float]) -> dict[str, str]:
        try:
            return {k: _sha(json.dumps(v, sort_keys=True)) for k, v in self._configs(x).items()}
        except ConfigError:
            return {}

    def records(self) -> list[Record]:
        """Every evaluation known (this session's and the earlier ones on disk), by index."""
        allr = {r.index: r for r in self.disk.values()}
        allr.update({r.index: r for r in self.session.values() if r.status != "pending"})
        return [allr[i] for i in sorted(allr)]

    # ------------------------------------------------------------------ dask
    def client(self, n_tasks: int):
        if self._client is None:
            from ..sweep import dask_client

            self._client = self._stack.enter_context(
                dask_client(
                    self.scheduler,
                    self.workers,
                    max(n_tasks, self.workers or 2),
                    "calibrate",
                    "task(s) in the first batch",
                )  # fmt: skip
            )
        return self._client

    def close(self) -> None:
        self._stack.close()
        self._client = None

    # ------------------------------------------------------------------ batches
    def evaluate(self, xs: list[list[float]], stage: str, budget: bool = True) -> list[Record]:
        """Records of the vectors ``xs`` (in order); new ones run as one dask batch.

        With ``budget``, raises :class:`BudgetExhausted` after the batch if it reached
        optimiser.max_evaluations (the vectors beyond it are not evaluated)."""
        cap = self.cal.spec.optimiser.max_evaluations
        keys, todo, exhausted = [], [], False
        for x in xs:
            k = tuple(float(v) for v in x)
            if k not in self.session:
                if budget and self.n_budget >= cap:
                    exhausted = True
                    break
                idx = len(self.order)
                self.order.append(k)
                if budget:
                    self.n_budget += 1
                old = self.disk.get(k)
                if old is not None:
                    if old.index != idx:
                        print(f"segmpm calibrate: note: evaluation {old.index:05d} is reused as "
                              f"the {idx}-th vector requested", file=sys.stderr)  # fmt: skip
                    self.session[k] = old
                    self.n_reused += 1
                else:
                    taken = {r.index for r in self.disk.values()}
                    taken |= {r.index for r in self.session.values()}
                    if idx in taken:  # only if a run differs from an earlier one: keep both
                        idx = max(taken) + 1
                    rec = Record(idx, list(k), stage, config_sha256=self._hashes(list(k)))
                    self.session[k] = rec
                    todo.append(rec)
            keys.append(k)
        if todo:
            self._run(todo)
        if exhausted:
            raise BudgetExhausted
        return [self.session[k] for k in keys]

    def _run(self, todo: list[Record]) -> None:
        from distributed import as_completed

        cal = self.cal
        client = self.client(len(todo) * len(cal.cases))
        futures: dict[Any, tuple[Record, int]] = {}
        pending: dict[int, list[dict[str, Any] | None]] = {}
        token = os.getpid()
        for rec in todo:
            try:
                configs = self._configs(rec.x)
            except ConfigError as err:  # a point whose configuration is invalid
                rec.status, rec.objective, rec.message = "failed", PENALTY, str(err)
                self._persist(rec)
                continue
            pending[rec.index] = [None] * len(cal.cases)
            for j, c in enumerate(cal.cases):
                run_dir = self.out / "evals" / f"{rec.index:05d}" / c.name
                tag = {"x": rec.x, "config_sha256": rec.config_sha256[c.name]}
                fut = client.submit(run_case, configs[c.name], str(run_dir.resolve()),
                                    str(c.reference_path), c.times, c.y_offset, tag,
                                    key=f"segmpm-eval-{rec.index:05d}-{c.name}-{token}",
                                    pure=False)  # fmt: skip
                futures[fut] = (rec, j)
        if self.on_batch is not None:
            self.on_batch(client, list(futures))
        try:
            for fut in as_completed(list(futures)):
                rec, j = futures[fut]
                try:
                    r = fut.result()
                except Exception as err:  # noqa: BLE001 - the task failed for good
                    r = {"status": "failed", "message": f"{type(err).__name__}: {err}"}
                slot = pending[rec.index]
                slot[j] = r
                if all(s is not None for s in slot):
                    self._finish(rec, slot)  # type: ignore[arg-type]
                    self.n_new += 1
                    if self.stop_after is not None and self.n_new >= self.stop_after:
                        raise KeyboardInterrupt
        except BaseException:
            for fut in futures:
                fut.cancel()
            raise
        if self.after_batch is not None:
            self.after_batch()

    def _finish(self, rec: Record, results: list[dict[str, Any]]) -> None:
        o = self.cal.spec.objective
        comb = combine(results, self.cal.cases, o.phi_weight, o.velocity_weight)
        rec.status, rec.objective = comb["status"], float(comb["objective"])
        rec.message, rec.cases, rec.residuals = comb["message"], comb["cases"], comb["residuals"]
        rec.wall_time_s = float(sum((r.get("wall_time_s") or 0.0) for r in results))
        self._persist(rec)
        msg = f" — {rec.message}" if rec.message else ""
        vals = ", ".join(
            f"{p.key}={v:.6g}" for p, v in zip(self.cal.parameters, rec.x, strict=True)
        )
        print(f"  eval {rec.index:05d} [{rec.stage}] {vals}: {rec.status}, objective "
              f"{rec.objective:.6g}{msg}", file=sys.stderr)  # fmt: skip

    def _persist(self, rec: Record) -> None:
        write_json(self.out / "evals" / f"{rec.index:05d}" / EVAL_FILE, rec.to_json())
        self.disk[tuple(rec.x)] = rec


# ---------------------------------------------------------------------------------- optimisers


def _x_of_z(cal: Calibration, z: np.ndarray) -> list[float]:
    return [p.to_x(float(v)) for p, v in zip(cal.parameters, z, strict=True)]


def _z_of_x(cal: Calibration, x: list[float]) -> np.ndarray:
    return np.asarray([p.to_z(v) for p, v in zip(cal.parameters, x, strict=True)])


def best_record(records: list[Record]) -> Record | None:
    """The completed evaluation with the lowest objective (the lowest index among ties), not
    counting the sensitivity batch."""
    ok = [r for r in records if r.status == "completed" and r.stage != "sensitivity"]
    return min(ok, key=lambda r: (r.objective, r.index)) if ok else None


def _residual_length(ev: Evaluator) -> int:
    for r in ev.records():
        if r.status == "completed":
            return len(r.residuals)
    return 0


def local_refine(ev: Evaluator, z0: np.ndarray) -> None:
    """scipy.optimize.least_squares (trf, bounds [0, 1]) on the per-bin residual vector from
    ``z0``; each Jacobian is a forward-difference batch of n evaluations run in parallel."""
    from scipy.optimize import least_squares

    cal, opt = ev.cal, ev.cal.spec.optimiser
    m = _residual_length(ev)
    if m == 0:
        return
    h = opt.fd_step
    penalty_r = np.full(m, math.sqrt(PENALTY / m))

    def residuals(rec: Record) -> np.ndarray:
        if rec.status != "completed" or len(rec.residuals) != m:
            return penalty_r
        return np.asarray(rec.residuals)

    def fun(z: np.ndarray) -> np.ndarray:
        return residuals(ev.evaluate([_x_of_z(cal, z)], "local")[0])

    def jac(z: np.ndarray) -> np.ndarray:
        r0 = fun(z)
        steps = np.where(z + h <= 1.0, h, -h)
        pts = []
        for j in range(z.size):
            zj = z.copy()
            zj[j] += steps[j]
            pts.append(_x_of_z(cal, zj))
        recs = ev.evaluate(pts, "jacobian")
        cols = []
        for j, rec in enumerate(recs):
            ok = rec.status == "completed" and len(rec.residuals) == m
            cols.append((residuals(rec) - r0) / steps[j] if ok else np.zeros(m))
        return np.column_stack(cols)

    z0 = np.clip(np.asarray(z0, dtype=float), 1e-9, 1 - 1e-9)
    tol = opt.tolerance
    least_squares(fun, z0, jac=jac, bounds=(0.0, 1.0), method="trf", ftol=tol, xtol=tol,
                  gtol=tol, max_nfev=opt.max_iterations, x_scale=1.0)  # fmt: skip


def lhs_then_local(ev: Evaluator) -> None:
    """A seeded Latin hypercube in the scaled coordinates, one batch, then :func:`local_refine`
    from its best point."""
    from scipy.stats import qmc

    cal, opt = ev.cal, ev.cal.spec.optimiser
    n = len(cal.parameters)
    k = opt.samples or 5 * n
    kw = "rng" if "rng" in inspect.signature(qmc.LatinHypercube).parameters else "seed"
    z = qmc.LatinHypercube(d=n, **{kw: opt.seed}).random(k)
    recs = ev.evaluate([_x_of_z(cal, row) for row in z], "lhs")
    best = best_record(recs)
    if best is not None:
        local_refine(ev, _z_of_x(cal, best.x))


def differential_evolution(ev: Evaluator) -> None:
    """scipy's differential evolution in the scaled coordinates, each generation one dask batch
    (``workers=`` a map-like callable, ``updating="deferred"``); optional polish."""
    from scipy.optimize import differential_evolution as de

    cal, opt = ev.cal, ev.cal.spec.optimiser
    n = len(cal.parameters)

    def mapper(_func: Any, zs: Any) -> list[float]:
        recs = ev.evaluate([_x_of_z(cal, np.asarray(z)) for z in zs], "de")
        return [r.objective if r.status == "completed" else PENALTY for r in recs]

    kw = "rng" if "rng" in inspect.signature(de).parameters else "seed"
    res = de(lambda z: PENALTY, bounds=[(0.0, 1.0)] * n, popsize=opt.popsize,
             maxiter=opt.max_iterations, tol=opt.tolerance, polish=False, updating="deferred",
             workers=mapper, init="latinhypercube", **{kw: opt.seed})  # fmt: skip
    if opt.polish:
        best = best_record(ev.records())
        local_refine(ev, _z_of_x(cal, best.x) if best is not None else res.x)


OPTIMISERS = {"lhs_then_local": lhs_then_local, "differential_evolution": differential_evolution}
