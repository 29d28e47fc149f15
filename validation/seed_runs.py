"""The seed chute case against the DEM reference, for each closure and μ_w (docs/validation.md).

Runs the default configuration (``segmpm run``) and one-setting variants to 20 s, each in
``validation/results/seed_chute/runs/<name>`` (resumable: an interrupted run continues from its
checkpoint), then compares each with ``validation/dem/reference_profiles.csv`` at 0.5–20 s and
writes ``compare_<name>.{json,png}`` and ``summary.json`` next to them. Usage::

    python validation/seed_runs.py [--end 20] [--only B A ...]

One run of the default takes a few minutes on one core (README); set NUMBA_NUM_THREADS=1 to leave
the other core free.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import shutil
import subprocess
import sys

HERE = pathlib.Path(__file__).parent
OUT = HERE / "results" / "seed_chute"
REF = HERE / "dem" / "reference_profiles.csv"

#: name → overrides of the default configuration
VARIANTS: dict[str, list[str]] = {
    "B": [],  # the default: reduced Hill–Tan, driver B
    "A": ["segregation.driver='A'"],
    "D": ["segregation.model='hill_tan_full'", "segregation.b_c_small=-0.02"],
    "F": ["segregation.model='fan2014'", "segregation.fan_S=2.1e-4"],
    "B_mw015": ["boundary.sidewall_friction=0.15"],
}
TIMES = [0.0, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0]


def run(name: str, end: float) -> pathlib.Path:
    """Run (or resume, or reuse) one variant to ``end``; returns its output folder."""
    out = OUT / "runs" / name
    info = out / "run.json"
    if info.exists():
        d = json.loads(info.read_text())
        if d.get("status") == "completed" and d.get("time_end") == end:
            return out
    times = [t for t in TIMES if t <= end]
    # the seed's local preset, which these studies are about (not the nonlocal default)
    cmd = [
        sys.executable,
        "-m",
        "segmpm.cli",
        "run",
        "chute_seed",
        "--out",
        str(out),
        "--no-progress",
    ]
    if (out / "checkpoint" / "state.npz").exists():
        cmd.append("--resume")
    else:
        for o in [*VARIANTS[name], f"time.end={end!r}", f"output.profile_times={times!r}",
                  "output.fields=false"]:  # fmt: skip
            cmd += ["--set", o]
    subprocess.run(cmd, check=True)
    return out


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--end", type=float, default=20.0)
    ap.add_argument("--only", nargs="+", choices=list(VARIANTS), default=list(VARIANTS))
    args = ap.parse_args()
    summary = {}
    for name in args.only:
        out = run(name, args.end)
        times = [str(t) for t in TIMES if 0 < t <= args.end]
        subprocess.run([sys.executable, "-m", "segmpm.cli", "compare", str(out), str(REF),
                        "--times", *times], check=True)  # fmt: skip
        shutil.copyfile(out / "compare.json", OUT / f"compare_{name}.json")
        shutil.copyfile(out / "figures" / "compare.png", OUT / f"compare_{name}.png")
        cmp = json.loads((out / "compare.json").read_text())
        info = json.loads((out / "run.json").read_text())
        summary[name] = {
            "overrides": VARIANTS[name],
            "wall_time_s": info.get("wall_time_s"),
            "steps": info.get("steps"),
            "per_time": cmp.get("per_time"),
        }
        (OUT / "summary.json").write_text(json.dumps(summary, indent=2))
        print(f"{name}: done", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
