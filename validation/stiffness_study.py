"""Stiffness-reduction study on the seed chute (issue: the default preset's evidence).

Runs the seed case (a preset, by default the seed's local model ``chute_seed``) at several
material.stiffness_scale values to a common horizon and compares the depth profiles of velocity
and small-grain fraction against the stiffest, at every profile time. Writes
validation/results/stiffness_study[_TAG].json and .png. Usage:
    python validation/stiffness_study.py [--end 1.0] [--scales 1 1e-2 1e-3]
        [--preset chute_seed | chute_nonlocal] [--tag TAG]
Each scale runs in its own output folder under validation/results/stiffness[_TAG]/ and can be
resumed.
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
PRESETS = pathlib.Path(__file__).parents[1] / "src" / "segmpm" / "presets"


def run(scale: float, end: float, preset: str, tag: str) -> pathlib.Path:
    out = OUT / f"stiffness{tag}" / f"scale_{scale:g}"
    done = out / "run.json"
    if done.exists() and json.loads(done.read_text()).get("status") == "completed":
        return out
    times = [t for t in (0.0, 0.25, 0.5, 1.0, 2.0, 5.0) if t <= end]
    if end not in times:
        times.append(end)
    config = PRESETS / f"{preset}.toml"
    cmd = [sys.executable, "-m", "segmpm.cli", "run", str(config), "--out", str(out), "--no-progress",
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
    ap.add_argument("--preset", default="chute_seed", choices=["chute_seed", "chute_nonlocal"])
    ap.add_argument("--tag", default="", help="suffix of the output names (e.g. _nonlocal)")
    args = ap.parse_args()
    OUT.mkdir(exist_ok=True)
    data = {}
    for s in args.scales:
        out = run(s, args.end, args.preset, args.tag)
        with xr.open_dataset(out / "profiles.nc", engine="h5netcdf") as ds:
            data[s] = ds.load()
        info = json.loads((out / "run.json").read_text())
        print(f"scale {s:g}: {info['steps']} steps, wall {info['wall_time_s']:.0f} s", flush=True)
    ref = data[max(args.scales)]
    summary = {"preset": args.preset, "end": args.end, "reference_scale": max(args.scales),
               "per_scale": {}}  # fmt: skip
    fig, axes = plt.subplots(1, 2, figsize=(9, 5), sharey=True)
    for s, ds in data.items():
        t = ds["time"].values
        per_time = {}
        for tt in t[t > 0]:
            i = int(np.argmin(np.abs(t - tt)))
            ir = int(np.argmin(np.abs(ref["time"].values - tt)))
            u, phi = ds["velocity_x"].values[i], ds["phi_small"].values[i]
            ur, phr = ref["velocity_x"].values[ir], ref["phi_small"].values[ir]
            ok = np.isfinite(u) & np.isfinite(ur)
            usurf = float(np.nanmax(ur))
            per_time[f"{tt:g}"] = {
                "surface_velocity": float(np.nanmax(u)),
                "surface_velocity_reference": usurf,
                "rms_velocity_vs_reference_over_surface": float(
                    np.sqrt(np.mean((u[ok] - ur[ok]) ** 2)) / usurf
                ),
                "rms_phi_vs_reference": float(np.sqrt(np.mean((phi[ok] - phr[ok]) ** 2))),
            }
        end = per_time[f"{t[np.argmin(np.abs(t - args.end))]:g}"]
        summary["per_scale"][f"{s:g}"] = {**end, "per_time": per_time}
        i = int(np.argmin(np.abs(t - args.end)))
        u, phi = ds["velocity_x"].values[i], ds["phi_small"].values[i]
        y = ds["y"].values * 1e3
        axes[0].plot(phi, y, label=f"scale {s:g}")
        axes[1].plot(u, y, label=f"scale {s:g}")
    axes[0].set_xlabel("φ_s")
    axes[1].set_xlabel("u (m/s)")
    axes[0].set_ylabel("y (mm)")
    axes[0].legend()
    fig.suptitle(f"seed chute ({args.preset}) at t = {args.end:g} s, stiffness scales")
    fig.tight_layout()
    fig.savefig(OUT / f"stiffness_study{args.tag}.png", dpi=120)
    (OUT / f"stiffness_study{args.tag}.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
