"""The ``segmpm`` command: run, validate, compare, plot, sweep, bench.

Exit codes (interface.md): 0 success; 2 invalid input; 3 numerical failure; 130 interrupted.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from . import __version__
from .config import ConfigError, load_config

EXIT_INVALID = 2


def _add_config_args(p: argparse.ArgumentParser, required: bool) -> None:
    p.add_argument("config", nargs=None if required else "?", help="configuration TOML file"
                   + ("" if required else " (default: the built-in seed chute case)"))  # fmt: skip
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override a configuration value, e.g. --set geometry.slope_deg=24 (TOML value)")  # fmt: skip


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``segmpm`` command."""
    ap = argparse.ArgumentParser(
        prog="segmpm",
        description="Material point method for dense granular flow with size segregation "
        "(Fei, Sun, Hill & Zhou 2017). Run with no configuration for the seed's chute case.",
        epilog="Exit codes: 0 success, 2 invalid input, 3 numerical failure, 130 interrupted.",
    )
    ap.add_argument("--version", action="version", version=f"segmpm {__version__}")
    sub = ap.add_subparsers(dest="command", metavar="COMMAND")

    p = sub.add_parser("run", help="run a simulation (default: the seed's chute case)")
    _add_config_args(p, required=False)
    p.add_argument("--out", help="output directory (default: output.dir of the configuration)")
    p.add_argument(
        "--resume", action="store_true", help="continue the run in --out from its last checkpoint"
    )
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

    p = sub.add_parser("bench", help="throughput benchmarks (particle-steps per second)")
    p.add_argument("--sizes", type=int, nargs="+", default=[8000, 32000], help="material points")
    p.add_argument("--threads", type=int, nargs="+", default=[1, 2], help="thread counts")
    p.add_argument("--steps", type=int, default=400, help="timed steps per block")
    p.add_argument("--repeats", type=int, default=5,
                   help="timed blocks per case (the median is reported)")  # fmt: skip
    p.add_argument("--json", dest="json_out", help="write the results to this JSON file")
    p.add_argument("--no-peer", action="store_true", help="skip the Taichi mpm88 peer")
    p.add_argument("--contended", action="store_true",
                   help="the step idle and beside a busy process, and the default run alone, "
                   "beside it and two at once (default sizes: 596 and 32000)")  # fmt: skip
    return ap


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
    except KeyboardInterrupt:
        print("segmpm: interrupted", file=sys.stderr)
        return 130


def _dispatch(args: argparse.Namespace) -> int:
    if args.command == "validate":
        cfg = load_config(args.config, args.overrides)
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
    if args.command == "bench":
        from .bench import run_bench, run_contended

        if args.contended:
            sizes = args.sizes if args.sizes != [8000, 32000] else [596, 32000]
            return run_contended(sizes, args.threads, args.steps, args.json_out, args.repeats)
        return run_bench(
            args.sizes, args.threads, args.steps, args.json_out, not args.no_peer, args.repeats
        )
    raise AssertionError(args.command)


def _run(args: argparse.Namespace) -> int:
    from .simulation import Simulation

    if args.resume:
        if not args.out:
            return _fail("--resume needs --out DIR (the directory of the run to continue)")
        out = Path(args.out)
        resolved = out / "config.toml"
        ckpt = out / "checkpoint" / "state.npz"
        if not resolved.exists() or not ckpt.exists():
            return _fail(f"--resume: no checkpoint to continue in {str(out)!r} "
                         f"(expected {resolved} and {ckpt})")  # fmt: skip
        if args.config is not None or args.overrides:
            return _fail("--resume continues the run with its saved configuration; "
                         "do not pass a configuration or --set")  # fmt: skip
        cfg = load_config(resolved)
    else:
        cfg = load_config(args.config, args.overrides)
        out = Path(args.out) if args.out else Path(cfg.output.dir)
    sim = Simulation(cfg, out_dir=out)
    print(f"segmpm {__version__}: {cfg.scenario.kind}, {sim.state.n} material points, "
          f"t_end = {cfg.time.end:g} s, {sim.threads} thread(s) ({sim.threads_reason}) → {out}",
          file=sys.stderr)  # fmt: skip
    res = sim.run(resume=args.resume, progress=False if args.no_progress else None)
    info = res.info
    pps = info.get("particle_steps_per_second")
    print(
        f"segmpm: {res.status} at t = {info['time']:.6g} s after {info['steps']} steps, "
        f"wall {info['wall_time_s']:.1f} s, "
        + (f"{pps:.3g} particle-steps/s" if pps else "no steps")
        + f"; mass drift {info['conservation']['mass_drift']:.2e}, "
        f"small-grain volume drift {info['conservation']['small_volume_drift']:.2e}",
        file=sys.stderr,
    )
    return res.exit_code


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
