"""``segmpm sweep SWEEP.toml``: an ensemble of ordinary runs over parameter values, on dask.distributed.

The sweep file (the public interface; README, "Command line")::

    base = "chute.toml"            # relative to the sweep file; or an inline [base] table of
                                   # configuration sections; absent = the built-in default
    mode = "product"               # default; "zip" pairs the lists (equal lengths required)

    [parameters]                   # configuration keys in the --set form, each with a list
    "segregation.c_D" = [4.0, 6.8, 10.0]
    "geometry.slope_deg" = [24.0, 26.0]

Members are numbered in the order of :func:`itertools.product` (the last key varies fastest) or of
the zipped lists, and run in ``OUT/members/NNNN/`` as ordinary runs (``config.toml``, ``run.json``,
``profiles.nc``, …). Every member's configuration is validated before any runs (exit 2 naming the
member and the key). On re-running the same sweep, a member whose ``run.json`` says "completed"
and whose ``config.toml`` holds its configuration (``grid.threads``, ``output.progress``,
``output.dir`` and ``time.chunk_steps`` may differ) is skipped; an interrupted member with a
checkpoint is resumed; any other member runs from the start, its folder cleared of segmpm's files
first. Each member holds the lock on its folder while it runs (``io.outdir.OutLock``).

Members run on a ``LocalCluster(n_workers=N, threads_per_worker=1, processes=True)`` (N = --workers,
default 2, at most the number of members to run) or on the scheduler given by ``--scheduler``
(whose workers must have segmpm installed and see OUT at the same path). Each member uses one
numba thread (``grid.threads`` of the configuration is set to 1 inside a sweep, and ``run.json``
says so).

``OUT/ensemble.nc`` gathers the members' ``profiles.nc`` along a ``member`` dimension (outer join
on ``time`` and ``y``, NaN where a member has no value), with one coordinate per swept parameter
named by its key (e.g. ``segregation.c_D``), and per member ``status`` and ``configuration`` (the
resolved TOML). ``OUT/sweep.json`` lists the members, their parameters, directories and status.
Exit code 0 if every member completed, 3 if any did not (they are listed), 2 on invalid input,
130 if interrupted.
"""

from __future__ import annotations

import contextlib
import copy
import itertools
import json
import math
import os
import sys
import time as _time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from . import __version__
from .config import (
    _SECTIONS,
    Config,
    ConfigError,
    default_data,
    load_config,
    read_toml,
    resolve_extends,
    validate_data,
)
from .io.atomic import write_json, write_with

EXIT_OK = 0
EXIT_INVALID = 2
EXIT_FAILED = 3
EXIT_INTERRUPTED = 130
SWEEP_KEYS = ("base", "mode", "parameters")


@dataclass
class Member:
    """One run of the ensemble."""

    index: int
    params: dict[str, Any]
    config: Config
    dir: Path
    status: str = "pending"
    action: str = "run"  # "skip", "resume" or "run"
    message: str = ""
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def name(self) -> str:
        return f"{self.index:04d}"

    def label(self) -> str:
        return ", ".join(f"{k}={v!r}" for k, v in self.params.items())


# ---------------------------------------------------------------------------------- the sweep file


def _read_sweep(path: Path) -> tuple[dict[str, Any], dict[str, list[Any]], str]:
    """(base data, parameters, mode) of a sweep file, raising :class:`ConfigError`."""
    doc = read_toml(path, "sweep")
    where = f"sweep file {str(path)!r}"
    unknown = [k for k in doc if k not in SWEEP_KEYS]
    if unknown:
        raise ConfigError(
            f"{where}: unknown key(s) {', '.join(repr(k) for k in unknown)}; allowed top-level "
            f"keys: {', '.join(SWEEP_KEYS)} (configuration sections go inside [base])"
        )
    base = doc.get("base")
    if base is None:
        data = default_data()
    elif isinstance(base, str):
        bp = Path(base)
        if not bp.is_absolute():
            bp = path.parent / bp
        try:
            data = resolve_extends(read_toml(bp), bp.parent)
        except ConfigError as err:
            raise ConfigError(f"{where}: base: {err}") from None
    elif isinstance(base, dict):
        try:  # an inline [base] may extend a preset or a file (relative to the sweep file)
            data = resolve_extends(copy.deepcopy(base), path.parent)
        except ConfigError as err:
            raise ConfigError(f"{where}: base: {err}") from None
    else:
        raise ConfigError(
            f"{where}: base = {base!r} must be a file name (string) or a table of configuration "
            "sections ([base])"
        )
    mode = doc.get("mode", "product")
    if mode not in ("product", "zip"):
        raise ConfigError(f"{where}: mode = {mode!r} is invalid; allowed: 'product', 'zip'")
    params = doc.get("parameters", {})
    if not isinstance(params, dict):
        raise ConfigError(f"{where}: parameters must be a table of key = [values]")
    for key, values in params.items():
        parts = key.split(".")
        if len(parts) != 2 or not all(p.strip() for p in parts):
            raise ConfigError(
                f"{where}: parameter key {key!r} must have the form section.key "
                f'(e.g. "segregation.c_D") with a section among {", ".join(_SECTIONS)}'
            )
        if parts[0] not in _SECTIONS:
            raise ConfigError(
                f"{where}: parameter key {key!r}: unknown section {parts[0]!r}; allowed "
                f"sections: {', '.join(_SECTIONS)}"
            )
        if not isinstance(values, list) or not values:
            raise ConfigError(
                f"{where}: parameters.{key!r} = {values!r} must be a non-empty list of values"
            )
    if mode == "zip" and params:
        lengths = {k: len(v) for k, v in params.items()}
        if len(set(lengths.values())) > 1:
            raise ConfigError(
                f"{where}: mode = 'zip' needs lists of equal length; got "
                + ", ".join(f"{k}: {n}" for k, n in lengths.items())
            )
    return data, params, mode


def _combinations(params: dict[str, list[Any]], mode: str) -> list[dict[str, Any]]:
    keys = list(params)
    if not keys:
        return [{}]
    rows = (
        zip(*params.values(), strict=True) if mode == "zip" else itertools.product(*params.values())
    )
    return [dict(zip(keys, r, strict=True)) for r in rows]


def build_members(sweep_path: str | Path, out: str | Path) -> tuple[list[Member], dict[str, Any]]:
    """Read the sweep and validate every member's configuration (raises :class:`ConfigError`)."""
    path = Path(sweep_path)
    data, params, mode = _read_sweep(path)
    members: list[Member] = []
    for i, combo in enumerate(_combinations(params, mode)):
        d = copy.deepcopy(data)
        for key, value in combo.items():
            section, name = key.split(".")
            sec = d.setdefault(section, {})
            if not isinstance(sec, dict):
                raise ConfigError(f"sweep member {i:04d}: base section '{section}' must be a table")
            sec[name] = value
        label = ", ".join(f"{k}={v!r}" for k, v in combo.items()) or "the base"
        try:
            cfg = validate_data(d)
        except ConfigError as err:
            raise ConfigError(f"sweep member {i:04d} ({label}): {err}") from None
        members.append(Member(i, combo, cfg, Path(out) / "members" / f"{i:04d}"))
    meta = {"sweep": str(path.resolve()), "mode": mode, "parameters": list(params)}
    return members, meta


# ---------------------------------------------------------------------------------- members


def _read_status(d: Path) -> str | None:
    try:
        return json.loads((d / "run.json").read_text()).get("status")
    except (OSError, ValueError, AttributeError):
        return None


def _plan(m: Member) -> None:
    """Decide whether ``m`` is skipped, resumed or run from the start."""
    from .io.outdir import RESUME_MAY_DIFFER, config_differences

    status = _read_status(m.dir)
    try:  # the member's run has its configuration (grid.threads = 1 in a sweep, progress, …)
        saved = load_config(m.dir / "config.toml")
    except ConfigError:
        same = False
    else:
        ignore = tuple(k for k in RESUME_MAY_DIFFER if k != "time.end")
        same = not config_differences(saved, m.config, may_differ=ignore)
    if status == "completed" and same and (m.dir / "profiles.nc").exists():
        m.action, m.status = "skip", "completed"
    elif (
        status in ("interrupted", "running")
        and same
        and (m.dir / "checkpoint" / "state.npz").exists()
    ):
        m.action = "resume"
    else:
        m.action = "run"


def run_member(config: dict[str, Any], out_dir: str, resume: bool) -> dict[str, Any]:
    """Run one member (inside a dask worker): an ordinary run with one numba thread."""
    os.environ["NUMBA_NUM_THREADS"] = "1"  # if numba is not imported yet in this worker
    t0 = _time.perf_counter()
    try:
        import numba

        numba.set_num_threads(1)
        from .io.outdir import OutLock, prepare_out_dir, remove_own_files
        from .simulation import Simulation

        # one thread per member (one member per core), recorded as such in its run.json
        config = {**config, "grid": {**config.get("grid", {}), "threads": 1}}
        cfg = validate_data(config)
        prepare_out_dir(out_dir)
        with OutLock(out_dir):  # another process running this member: LockedError
            if not resume:  # a member that runs from the start leaves no stale file behind
                remove_own_files(out_dir)
            res = Simulation(cfg, out_dir=out_dir).run(resume=resume, progress=False, lock=False)
        info = res.info
        msg = (info.get("failure") or {}).get("message", "")
        return {"status": res.status, "exit_code": res.exit_code, "message": msg,
                "time": info.get("time"), "wall_time_s": _time.perf_counter() - t0}  # fmt: skip
    except ConfigError as err:  # the member's folder is unusable or locked: do not touch it
        return {"status": "failed", "exit_code": EXIT_INVALID, "message": str(err),
                "time": None, "wall_time_s": _time.perf_counter() - t0}  # fmt: skip
    except Exception as err:  # an unexpected error fails this member, not the sweep
        msg = f"{type(err).__name__}: {err}"
        info = {"status": "failed", "segmpm_version": __version__,
                "failure": {"reason": "exception", "message": msg}}  # fmt: skip
        try:
            write_json(Path(out_dir) / "run.json", info)
        except OSError:
            pass
        return {"status": "failed", "exit_code": EXIT_FAILED, "message": msg,
                "time": None, "wall_time_s": _time.perf_counter() - t0}  # fmt: skip


@contextlib.contextmanager
def dask_client(scheduler: str | None, workers: int, n_tasks: int, what: str = "sweep",
                unit: str = "member(s)") -> Iterator[Any]:  # fmt: skip
    """A dask.distributed client: on ``scheduler`` if given, else on a ``LocalCluster`` of
    ``min(workers or 2, n_tasks)`` worker processes with one thread each and
    ``NUMBA_NUM_THREADS=1`` (one member per core). Closed (with its cluster) on exit.

    Raises :class:`ConfigError` when the scheduler cannot be reached (exit 2). Shared by
    ``segmpm sweep`` and ``segmpm calibrate``."""
    import logging

    from distributed import Client, LocalCluster

    cluster = None
    if scheduler:
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError, ValueError) as err:
            raise ConfigError(f"--scheduler {scheduler!r}: cannot connect: {err}") from None
    else:
        n = max(1, min(workers or 2, n_tasks))
        cluster = LocalCluster(
            n_workers=n,
            threads_per_worker=1,
            processes=True,
            dashboard_address=None,
            silence_logs=logging.ERROR,
            env={"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"},
        )
        client = Client(cluster)
    where = (
        client.scheduler.address if cluster is None else f"{len(cluster.workers)} local worker(s)"
    )
    print(f"segmpm {what}: {n_tasks} {unit} on {where}", file=sys.stderr)
    try:
        yield client
    finally:
        client.close()
        if cluster is not None:
            cluster.close()


def _execute(todo: list[Member], scheduler: str | None, workers: int) -> None:
    """Run ``todo`` on dask.distributed, updating each member's status as results arrive."""
    from distributed import as_completed

    with dask_client(scheduler, workers, len(todo)) as client:
        futures = {}
        for m in todo:
            m.dir.mkdir(parents=True, exist_ok=True)
            fut = client.submit(run_member, m.config.to_dict(), str(m.dir.resolve()),
                                m.action == "resume", key=f"segmpm-member-{m.name}-{os.getpid()}",
                                pure=False)  # fmt: skip
            futures[fut] = m
        for fut in as_completed(list(futures)):
            m = futures[fut]
            try:
                r = fut.result()
            except Exception as err:  # worker died, cancelled, …
                r = {"status": "failed", "message": f"{type(err).__name__}: {err}"}
            m.status = r.get("status", "failed")
            m.message = r.get("message", "")
            m.extra = {k: r.get(k) for k in ("time", "wall_time_s")}
            wall = m.extra.get("wall_time_s")
            print(f"  member {m.name} ({m.label()}): {m.status}"
                  + (f" in {wall:.1f} s" if wall else "") + (f" — {m.message}" if m.message else ""),
                  file=sys.stderr)  # fmt: skip


# ---------------------------------------------------------------------------------- ensemble.nc


def _coord_values(values: list[Any]):
    import numpy as np

    if all(isinstance(v, bool) for v in values):
        return np.asarray(values, dtype=bool)
    if all(isinstance(v, int | float) and not isinstance(v, bool) for v in values):
        return np.asarray(values, dtype=float if any(isinstance(v, float) for v in values) else int)
    return np.asarray([v if isinstance(v, str) else json.dumps(v) for v in values], dtype=str)


def gather(members: list[Member], meta: dict[str, Any], out: Path) -> Path:
    """Write ``OUT/ensemble.nc`` from the members' ``profiles.nc`` (atomically)."""
    import numpy as np
    import xarray as xr

    dss: list[xr.Dataset | None] = []
    for m in members:
        p = m.dir / "profiles.nc"
        ds = None
        if p.exists():
            try:
                with xr.open_dataset(p, engine="h5netcdf") as f:
                    ds = f.load()
            except Exception:  # unreadable partial output of a failed member
                ds = None
        if ds is not None:
            ds.attrs = {}
            if "y_edges" in ds:
                ds = ds.drop_vars("y_edges")
        dss.append(ds)
    template = next((d for d in dss if d is not None), None)
    if template is None:
        ens = xr.Dataset(coords={"member": np.arange(len(members))})
    else:
        empty = template.isel(time=slice(0, 0))
        dss = [d if d is not None else empty for d in dss]
        ens = xr.concat(dss, dim="member", join="outer", data_vars="all", coords="different", compat="equals",
                        combine_attrs="drop")  # fmt: skip
        ens = ens.assign_coords(member=np.arange(len(members)))
    for key in meta["parameters"]:
        vals = _coord_values([m.params[key] for m in members])
        ens = ens.assign_coords({key: ("member", vals, {"long_name": f"swept parameter {key}"})})
    ens["status"] = ("member", np.asarray([m.status for m in members], dtype=str))
    ens["configuration"] = ("member", np.asarray([m.config.to_toml() for m in members], dtype=str))
    ens["member"].attrs["long_name"] = "ensemble member (OUT/members/NNNN)"
    ens.attrs = {
        "title": "segmpm ensemble of depth profiles",
        "segmpm_version": __version__,
        "sweep": meta["sweep"],
        "mode": meta["mode"],
        "parameters": ", ".join(meta["parameters"]),
    }
    path = out / "ensemble.nc"
    write_with(path, lambda tmp: ens.to_netcdf(tmp, engine="h5netcdf"))
    return path


def _manifest(members: list[Member], meta: dict[str, Any], out: Path) -> None:
    rows = [
        {
            "member": m.index,
            "dir": str(m.dir),
            "parameters": m.params,
            "status": m.status,
            "action": m.action,
            "message": m.message,
        }  # fmt: skip
        for m in members
    ]
    clean = json.loads(json.dumps(rows, default=str))
    for r in clean:
        for k, v in r["parameters"].items():
            if isinstance(v, float) and not math.isfinite(v):
                r["parameters"][k] = str(v)
    write_json(out / "sweep.json", {**meta, "members": clean})


# ---------------------------------------------------------------------------------- entry point


def run_sweep(sweep_path: str | Path, out: str | Path = "sweep-out", scheduler: str | None = None,
              workers: int = 0) -> int:  # fmt: skip
    """CLI entry point of ``segmpm sweep``; returns the exit code."""
    if workers is not None and workers < 0:
        print(f"segmpm: error: --workers = {workers} must be ≥ 0 (0 = default, 2)", file=sys.stderr)
        return EXIT_INVALID
    out = Path(out)
    try:
        members, meta = build_members(sweep_path, out)
    except ConfigError as err:
        print(f"segmpm: error: {err}", file=sys.stderr)
        return EXIT_INVALID
    for m in members:
        _plan(m)
    todo = [m for m in members if m.action != "skip"]
    skipped = len(members) - len(todo)
    print(f"segmpm sweep: {len(members)} member(s) ({meta['mode']}), {skipped} already completed, "
          f"{len(todo)} to run → {out}", file=sys.stderr)  # fmt: skip
    out.mkdir(parents=True, exist_ok=True)
    _manifest(members, meta, out)
    interrupted = False
    if todo:
        try:
            _execute(todo, scheduler, workers or 0)
        except ConfigError as err:
            print(f"segmpm: error: {err}", file=sys.stderr)
            return EXIT_INVALID
        except KeyboardInterrupt:
            interrupted = True
            for m in todo:
                if m.status == "pending":
                    m.status = _read_status(m.dir) or "interrupted"
                    if m.status == "running":
                        m.status = "interrupted"
    _manifest(members, meta, out)
    path = gather(members, meta, out)
    bad = [m for m in members if m.status != "completed"]
    print(f"segmpm sweep: wrote {path}", file=sys.stderr)
    if interrupted:
        print("segmpm sweep: interrupted; re-run the same command to continue", file=sys.stderr)
        return EXIT_INTERRUPTED
    if bad:
        print(f"segmpm sweep: {len(bad)} member(s) did not complete:", file=sys.stderr)
        for m in bad:
            print(f"  {m.name} ({m.label()}): {m.status}" + (f" — {m.message}" if m.message else ""),
                  file=sys.stderr)  # fmt: skip
        return EXIT_FAILED
    print(f"segmpm sweep: all {len(members)} member(s) completed", file=sys.stderr)
    return EXIT_OK
