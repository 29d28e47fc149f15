"""The ``segmpm`` command: run, validate, compare, plot, sweep, calibrate, predict, bench.

Exit codes: 0 success; 2 invalid input (configuration, output directory, a locked or occupied
``--out``, a changed configuration on ``--resume``); 3 numerical failure; 4 an output or checkpoint
could not be written mid-run; 130 interrupted.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from . import __version__
from .config import Config, ConfigError, load_config, read_toml, validate_data
from .io.atomic import OutputWriteError
from .io.outdir import RESUME_MAY_DIFFER, config_differences

EXIT_INVALID = 2
EXIT_WRITE = 4


def _add_config_args(p: argparse.ArgumentParser, required: bool) -> None:
    p.add_argument("config", nargs=None if required else "?",
                   help="configuration TOML file or a built-in preset name (chute_nonlocal, "
                   "chute_seed)" + ("" if required else "; default: the seed chute case with the "
                   "grain-calibrated nonlocal model, preset chute_nonlocal"))  # fmt: skip
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a configuration value, e.g. --set geometry.slope_deg=24 (TOML value)")  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``segmpm`` command."""
    ap = argparse.ArgumentParser(
        prog="segmpm",
        description="Material point method for dense granular flow with size segregation "
        "(Fei, Sun, Hill & Zhou 2017). Run with no configuration for the seed's chute case (the "
        "grain-calibrated nonlocal model; `segmpm run chute_seed` for the seed's local model).",
        epilog="Exit codes: 0 success, 2 invalid input, 3 numerical failure, 4 an output could "
        "not be written mid-run, 130 interrupted.",
    )
    ap.add_argument("--version", action="version", version=f"segmpm {__version__}")
    sub = ap.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser(
        "run", help="run a simulation (default: the seed's chute case, nonlocal model)"
    )
    _add_config_args(p, required=False)
    p.add_argument("--out", help="output directory (default: output.dir of the configuration)")
    g = p.add_mutually_exclusive_group()
    g.add_argument("--resume", action="store_true",
                   help="start the run in --out, or continue it from its last checkpoint, or do "
                   "nothing if it is complete: the same command line after every preemption. "
                   "With CONFIG/--set the configuration must be the run's (only "
                   f"{', '.join(RESUME_MAY_DIFFER)} may differ); without, --out's config.toml "
                   "is used")  # fmt: skip
    g.add_argument("--overwrite", action="store_true",
                   help="replace the run in --out: remove segmpm's own files there first "
                   "(profiles.nc, run.json, config.toml, compare.json, checkpoint/, "
                   "fields/particles*, figures/profiles.png and compare.png); other files are "
                   "kept")  # fmt: skip
    p.add_argument("--no-progress", action="store_true", help="no progress bar")

    p = sub.add_parser("validate", help="check a configuration and print the resolved one")
    _add_config_args(p, required=True)

    p = sub.add_parser("compare", help="error norms of a run's profiles against a reference CSV")
    p.add_argument("out_dir", help="output directory of a run")
    p.add_argument("reference", help="reference CSV (time_s, y_m, phi_small, velocity_x)")
    p.add_argument("--times", type=float, nargs="+", help="times to compare (default: all common)")
    p.add_argument("--y-offset", type=float, default=0.0,
                   help="added to the reference's y_m before comparing (datum shift), m")  # fmt: skip

    p = sub.add_parser("plot", help="standard figures of a finished or running run")
    p.add_argument("out_dir", help="output directory of a run")

    p = sub.add_parser("sweep", help="an ensemble of runs over parameter values (dask.distributed)")
    p.add_argument("sweep", help="SWEEP.toml")
    p.add_argument("--out", default="sweep-out", help="output directory of the ensemble")
    p.add_argument("--scheduler", help="address of a dask scheduler (default: a local cluster)")
    p.add_argument("--workers", type=int, default=0, help="local workers (default: cores)")

    p = sub.add_parser("calibrate", help="fit configuration keys to reference profiles "
                       "(dask.distributed; docs/calibrate.md)")  # fmt: skip
    p.add_argument("cal", help="CAL.toml (parameters, cases, objective, optimiser, inner model)")
    p.add_argument("--out", default="calibrate-out",
                   help="output directory (re-running the same command continues a calibration)")  # fmt: skip
    p.add_argument("--scheduler", help="address of a dask scheduler (default: a local cluster)")
    p.add_argument("--workers", type=int, default=0, help="local workers (default: 2)")
    p.add_argument(
        "--predict",
        metavar="HELDOUT.toml",
        help="after the fit, run its parameters on these held-out cases (as predict)",
    )

    p = sub.add_parser("predict", help="run calibrated parameters on held-out cases: the "
                       "cross-validation table")  # fmt: skip
    p.add_argument("cal_out", help="output directory of segmpm calibrate")
    p.add_argument("--cases", help="TOML file of [[cases]] held out of the fit (default: none, "
                   "only the fit cases)")  # fmt: skip
    p.add_argument("--out", help="output directory (default: CAL_OUT/predict)")
    p.add_argument("--scheduler", help="address of a dask scheduler (default: a local cluster)")
    p.add_argument("--workers", type=int, default=0, help="local workers (default: 2)")

    p = sub.add_parser("bench", help="throughput benchmarks (particle-steps per second)")
    p.add_argument("--sizes", type=int, nargs="+", default=[8000, 32000], help="material points")
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="thread counts")
    p.add_argument("--steps", type=int, default=400, help="timed steps per block")
    p.add_argument("--repeats", type=int, default=5,
                   help="timed blocks per case (the median is reported)")  # fmt: skip
    p.add_argument("--json", dest="json_out", help="write the results to this JSON file")
    p.add_argument("--no-peer", action="store_true", help="skip the Taichi mpm88 peer")
    p.add_argument("--variants", nargs="+", default=["local"], choices=BENCH_VARIANTS,
                   help="models timed, interleaved (the first is the reference of the cost "
                   "ratio): the local default and the grain-calibrated nonlocal model")  # fmt: skip
    p.add_argument("--contended", action="store_true",
                   help="the step idle and beside a busy process, and the default run alone, "
                   "beside it and two at once (default sizes: 596 and 32000)")  # fmt: skip
    return ap


#: ``segmpm bench --variants`` (segmpm.bench.VARIANTS; listed here so that the parser does not
#: import the compiled kernels)
BENCH_VARIANTS = ["local", "nonlocal"]


def _fail(msg: str) -> int:
    print(f"segmpm: error: {msg}", file=sys.stderr)
    return EXIT_INVALID


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``segmpm`` console script."""
    ap = build_parser()
    try:
        args = ap.parse_args(argv)
    except SystemExit as e:  # argparse exits 2 on bad arguments, 0 on --help
        return int(e.code or 0)
    if args.command is None:
        ap.print_help()
        return 0
    try:
        return _dispatch(args)
    except ConfigError as e:
        return _fail(str(e))
    except OutputWriteError as e:
        print(f"segmpm: error: {e}", file=sys.stderr)
        return EXIT_WRITE
    except KeyboardInterrupt:
        print("segmpm: interrupted", file=sys.stderr)
        return 130


def _note_without_extends(path: str | None) -> None:
    """A file without ``extends`` starts from the schema's defaults, which are not the default
    preset's (a 12 mm strip at full stiffness): say so, once, before the run or the listing."""
    if path is None:
        return
    try:
        data = read_toml(path)
    except ConfigError:
        return  # load_config reports it
    if "extends" not in data:
        print(f"segmpm: note: {path} has no `extends`: the keys it does not set take the schema's "
              "defaults (stiffness scale 1, CFL 0.4, a 12 mm strip), not those of the default "
              "preset; start it with extends = \"chute_seed\" to build on the preset",
              file=sys.stderr)  # fmt: skip


def _dispatch(args: argparse.Namespace) -> int:
    if args.command == "validate":
        cfg = load_config(args.config, args.overrides)
        _note_without_extends(args.config)
        print(cfg.to_toml())
        print(f"# configuration is valid ({args.config})", file=sys.stderr)
        return 0
    if args.command == "run":
        return _run(args)
    if args.command == "compare":
        from .analysis.compare import compare_run

        return compare_run(args.out_dir, args.reference, args.times, args.y_offset)
    if args.command == "plot":
        return _plot(Path(args.out_dir))
    if args.command == "sweep":
        from .sweep import run_sweep

        return run_sweep(args.sweep, args.out, args.scheduler, args.workers)
    if args.command == "calibrate":
        from .calibrate import run_calibrate

        return run_calibrate(args.cal, args.out, args.scheduler, args.workers, args.predict)
    if args.command == "predict":
        from .calibrate import run_predict

        return run_predict(args.cal_out, args.cases, args.out, args.scheduler, args.workers)
    if args.command == "bench":
        from .bench import run_bench, run_contended

        if args.contended:
            sizes = args.sizes if args.sizes != [8000, 32000] else [596, 32000]
            return run_contended(sizes, args.threads, args.steps, args.json_out, args.repeats)
        return run_bench(
            args.sizes,
            args.threads,
            args.steps,
            args.json_out,
            not args.no_peer,
            args.repeats,
            tuple(args.variants),
        )
    raise AssertionError(args.command)


def _same_time(a: float, b: float) -> bool:
    return abs(a - b) <= 1e-12 * max(1.0, abs(b))


def _plan_resume(out: Path, cfg: Config, explicit: bool) -> tuple[str, str]:
    """What ``--resume`` does in OUT: ("start" | "continue" | "complete", a sentence).

    Raises OutDirError (exit 2) when the configuration differs from the run's in other keys
    than :data:`RESUME_MAY_DIFFER`, the checkpoint cannot be read, or it lies after time.end."""
    from .io.checkpoint import load_checkpoint
    from .io.outdir import OutDirError, read_run_info

    saved_path, ckpt = out / "config.toml", out / "checkpoint" / "state.npz"
    meta = None
    if ckpt.is_file():
        try:
            meta = load_checkpoint(ckpt)[1]
        except Exception as err:  # noqa: BLE001 - any damage: name it, start nothing
            raise OutDirError(f"--resume: the checkpoint {str(ckpt)!r} cannot be read ({err}); "
                              "use --overwrite to start the run again") from None  # fmt: skip
    saved, source = None, None
    if saved_path.is_file():
        saved, source = load_config(saved_path), str(saved_path)
    elif meta is not None:
        try:
            saved = validate_data(meta["configuration"])
        except (ConfigError, KeyError, TypeError):
            saved = None
        source = f"{ckpt} (no config.toml)"
    if explicit and saved is not None:
        diff = config_differences(saved, cfg)
        if diff:
            listed = "; ".join(
                f"{k} = {new!r} (the run in OUT has {old!r})" for k, old, new in diff
            )
            raise OutDirError(
                f"--resume: the configuration differs from that of the run in {str(out)!r} "
                f"({source}) in {len(diff)} key(s): {listed}. Only "
                f"{', '.join(RESUME_MAY_DIFFER)} may differ on --resume; use --overwrite to "
                "start again with this configuration, or another --out"
            )
    info = read_run_info(out) or {}
    end = cfg.time.end
    if meta is None:
        if info.get("status") == "completed" and saved is not None:
            t = float(info.get("time", float("nan")))
            if _same_time(t, end):
                return "complete", f"t = {t:.6g} s"
            raise OutDirError(f"--resume: the run in {str(out)!r} is complete at t = {t:.6g} s but "
                              f"its checkpoint ({ckpt}) is gone, so it cannot continue to "
                              f"time.end = {end:g} s; use --overwrite to run it again")  # fmt: skip
        return "start", "no checkpoint in OUT"
    t = float(meta["time"])
    if info.get("status") == "completed" and _same_time(t, end):
        return "complete", f"t = {t:.6g} s"
    if t > end and not _same_time(t, end):
        raise OutDirError(f"--resume: the run in {str(out)!r} is at t = {t:.6g} s, after "
                          f"time.end = {end:g} s (a run cannot be shortened); use --overwrite "
                          "to start again")  # fmt: skip
    return "continue", f"from its checkpoint at t = {t:.6g} s"


def _run(args: argparse.Namespace) -> int:
    from .io.outdir import (
        OutDirError,
        OutLock,
        describe_contents,
        foreign_files,
        own_files,
        prepare_out_dir,
        remove_own_files,
    )
    from .simulation import Simulation

    explicit = args.config is not None or bool(args.overrides)
    if args.resume:
        if not args.out and not explicit:
            return _fail("--resume needs --out DIR (the directory of the run to continue)")
        if explicit:
            cfg = load_config(args.config, args.overrides)
            out = Path(args.out) if args.out else Path(cfg.output.dir)
        else:
            out = Path(args.out)
            saved = out / "config.toml"
            if out.exists() and not out.is_dir():
                prepare_out_dir(out)  # names the problem: --out is a file
            if not saved.is_file():
                return _fail(f"--resume: no checkpoint to continue in {str(out)!r} (no {saved}); "
                             "to start a run that the same command line continues after a "
                             "preemption, give its configuration: segmpm run CASE.toml "
                             f"--out {out} --resume")  # fmt: skip
            cfg = load_config(saved)
    else:
        cfg = load_config(args.config, args.overrides)
        out = Path(args.out) if args.out else Path(cfg.output.dir)
    if args.config is not None:
        _note_without_extends(args.config)
    prepare_out_dir(out)
    with OutLock(out):
        resume = False
        if args.resume:
            action, why = _plan_resume(out, cfg, explicit)
            if action == "complete":
                print(f"segmpm: the run in {out} is already complete ({why}, time.end = "
                      f"{cfg.time.end:g} s); nothing to do", file=sys.stderr)  # fmt: skip
                return 0
            if action == "start":
                # files of an earlier start that did not reach its first checkpoint
                stale = [p for p in remove_own_files(out) if p.name != "config.toml"]
                note = f"; removed {len(stale)} file(s) of an earlier start" if stale else ""
                print(f"segmpm: --resume: {why}: starting the run{note}", file=sys.stderr)
            else:
                resume = True
                print(f"segmpm: --resume: continuing the run in {out} {why}", file=sys.stderr)
        else:
            what = describe_contents(out)
            if what is not None and not args.overwrite:
                if own_files(out):
                    hint = ("use --resume to continue it (same configuration, time.end may grow), "
                            "--overwrite to replace it (removes only segmpm's files), or another "
                            "--out")  # fmt: skip
                else:
                    hint = ("use --overwrite to write the run there anyway (segmpm's own files "
                            "only are created or replaced; the other files are kept), or "
                            "another --out")  # fmt: skip
                raise OutDirError(f"--out {str(out)!r} already holds {what}; not overwriting it "
                                  f"silently: {hint}")  # fmt: skip
            if args.overwrite:
                removed = remove_own_files(out)
                kept = len(foreign_files(out))
                if removed or kept:
                    print(f"segmpm: --overwrite: removed {len(removed)} segmpm file(s) from {out}"
                          + (f", kept {kept} other file(s)" if kept else ""),
                          file=sys.stderr)  # fmt: skip
        try:
            sim = Simulation(cfg, out_dir=out)  # generates and compiles (or loads) the kernels
        except OSError as err:
            return _cache_write_failure(err)
        print(f"segmpm {__version__}: {cfg.scenario.kind}, {sim.engine.n} material points, "
              f"t_end = {cfg.time.end:g} s, {sim.threads} thread(s) ({sim.threads_reason}) → {out}",
              file=sys.stderr)  # fmt: skip
        sim.announce = True  # the estimated steps and wall time, after the first steps
        res = sim.run(resume=resume, progress=False if args.no_progress else None, lock=False)
    info = res.info
    pps = info.get("particle_steps_per_second")
    compile_s = info.get("compile_s") or 0.0
    print(
        f"segmpm: {res.status} at t = {info['time']:.6g} s after {info['steps']} steps, "
        f"wall {info['wall_time_s']:.1f} s"
        + (f" (+ {compile_s:.1f} s compile/cache load)" if compile_s >= 0.05 else "")
        + ", "
        + (f"{pps:.3g} particle-steps/s" if pps else "no steps")
        + f"; mass drift {info['conservation']['mass_drift']:.2e}, "
        f"small-grain volume drift {info['conservation']['small_volume_drift']:.2e}",
        file=sys.stderr,
    )
    return res.exit_code


def _cache_write_failure(err: OSError) -> int:
    """The kernels' generated sources or compiled code could not be written (exit 4): the run
    has not started, so nothing of it is lost."""
    from ._cache import KERNEL_CACHE

    path = err.filename or KERNEL_CACHE
    cause = err.strerror or str(err) or type(err).__name__
    print(f"segmpm: error: the kernels could not be written to the kernel cache ({path}: "
          f"{cause}); the run has not started. Free space there, or point SEGMPM_CACHE_DIR at "
          f"a writable directory (in use: {KERNEL_CACHE})", file=sys.stderr)  # fmt: skip
    return EXIT_WRITE


def _plot(out: Path) -> int:
    import xarray as xr

    from .io.figures import plot_profiles

    path = out / "profiles.nc"
    if not path.exists():
        return _fail(f"no profiles.nc in {str(out)!r}")
    with xr.open_dataset(path, engine="h5netcdf") as ds:
        fig = plot_profiles(ds.load(), out / "figures" / "profiles.png")
    info = out / "run.json"
    status = json.loads(info.read_text()).get("status") if info.exists() else "unknown"
    print(f"wrote {fig} (run status: {status})")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
