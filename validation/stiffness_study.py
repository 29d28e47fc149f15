"""Stiffness-reduction study on the seed chute (issue: the default preset's evidence).

Runs the seed case (default configuration) at material.stiffness_scale = 1, 1e-2 and 1e-3 to a
common horizon and compares the depth profiles of velocity and small-grain fraction. Writes
validation/results/stiffness_study.json and .png. Usage:
    python validation/stiffness_study.py [--end 1.0] [--scales 1 1e-2 1e-3]
Each scale runs in its own output folder under validation/results/stiffness/ and can be resumed.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import xarray as xr  # noqa: E402

OUT = pathlib.Path(__file__).parent / "results"


def run(scale: float, end: float) -> pathlib.Path:
    out = OUT / "stiffness" / f"scale_{scale:g}"
    done = out / "run.json"
    if done.exists() and json.loads(done.read_text()).get("status") == "completed":
        return out
    times = [t for t in (0.0, 0.25, 0.5, 1.0, 2.0, 5.0) if t <= end]
    if end not in times:
        times.append(end)
    cmd = [sys.executable, "-m", "segmpm.cli", "run", "--out", str(out), "--no-progress",
           "--set", f"material.stiffness_scale={scale!r}", "--set", f"time.end={end!r}",
           "--set", f"output.profile_times={times!r}", "--set", "output.fields=false",
           "--set", "output.checkpoint_interval=0.1"]  # fmt: skip
    if (out / "checkpoint" / "state.npz").exists():
        cmd = [
            sys.executable,
            "-m",
            "segmpm.cli",
            "run",
            "--resume",
            "--out",
            str(out),
            "--no-progress",
        ]
    subprocess.run(cmd, check=True)
    return out


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--end", type=float, default=1.0)
    ap.add_argument("--scales", type=float, nargs="+", default=[1.0, 1e-2, 1e-3])
    args = ap.parse_args()
    OUT.mkdir(exist_ok=True)
    data = {}
    for s in args.scales:
        with xr.open_dataset(run(s, args.end) / "profiles.nc", engine="h5netcdf") as ds:
            data[s] = ds.load()
        info = json.loads((OUT / "stiffness" / f"scale_{s:g}" / "run.json").read_text())
        print(f"scale {s:g}: {info['steps']} steps, wall {info['wall_time_s']:.0f} s", flush=True)
    ref = data[max(args.scales)]
    summary = {"end": args.end, "reference_scale": max(args.scales), "per_scale": {}}
    fig, axes = plt.subplots(1, 2, figsize=(9, 5), sharey=True)
    for s, ds in data.items():
        t = ds["time"].values
        i = int(np.argmin(np.abs(t - args.end)))
        u, phi = ds["velocity_x"].values[i], ds["phi_small"].values[i]
        ur, phr = ref["velocity_x"].values[i], ref["phi_small"].values[i]
        ok = np.isfinite(u) & np.isfinite(ur)
        usurf = float(np.nanmax(ur))
        summary["per_scale"][f"{s:g}"] = {
            "surface_velocity": float(np.nanmax(u)),
            "rms_velocity_vs_reference_over_surface": float(
                np.sqrt(np.mean((u[ok] - ur[ok]) ** 2)) / usurf
            ),
            "rms_phi_vs_reference": float(np.sqrt(np.mean((phi[ok] - phr[ok]) ** 2))),
        }
        y = ds["y"].values * 1e3
        axes[0].plot(phi, y, label=f"scale {s:g}")
        axes[1].plot(u, y, label=f"scale {s:g}")
    axes[0].set_xlabel("φ_s")
    axes[1].set_xlabel("u (m/s)")
    axes[0].set_ylabel("y (mm)")
    axes[0].legend()
    fig.suptitle(f"seed chute at t = {args.end:g} s for three stiffness scales")
    fig.tight_layout()
    fig.savefig(OUT / "stiffness_study.png", dpi=120)
    (OUT / "stiffness_study.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
