#!/usr/bin/env python
"""The column model against the 2-D MPM on the seed case (issue: column vs MPM at 1, 5, 20 s).

For each preset (``chute_nonlocal``, the default, and the seed's local ``chute_seed``) both
solvers run the 20 s seed case as ordinary ``segmpm run`` calls into
validation/results/column/PRESET/{mpm,column} (completed runs are reused), and the column's
profiles are compared with the MPM's at 1, 5 and 20 s: surface speed (``compare``'s definition),
velocity RMS over the MPM's surface speed, φ_s RMS, on the output bins both fill. Writes
validation/results/column/summary.{json,md} with the wall times (on this machine, one thread).

    python validation/column_vs_mpm.py [--presets chute_nonlocal chute_seed] [--end 20]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import xarray as xr

from segmpm.analysis.compare import surface_velocity

HERE = Path(__file__).resolve().parent
OUT = HERE / "results" / "column"
TIMES = (1.0, 5.0, 20.0)


def run(preset: str, solver: str, end: float) -> Path:
    out = OUT / preset / solver
    info = out / "run.json"
    if info.exists() and json.loads(info.read_text()).get("status") == "completed":
        return out
    times = sorted({0.0, *[t for t in TIMES if t <= end], end})
    cmd = [sys.executable, "-m", "segmpm.cli", "run", preset, "--out", str(out), "--no-progress",
           "--set", f"scenario.solver='{solver}'", "--set", f"time.end={end!r}",
           "--set", f"output.profile_times={times!r}", "--set", "output.fields=false"]  # fmt: skip
    if out.exists():
        cmd.append("--resume")
    subprocess.run(cmd, check=True)
    return out


def compare(preset: str, end: float) -> dict:
    ds = {}
    for solver in ("mpm", "column"):
        with xr.open_dataset(run(preset, solver, end) / "profiles.nc", engine="h5netcdf") as d:
            ds[solver] = d.load()
    res: dict = {"preset": preset, "per_time": {}}
    for solver in ("mpm", "column"):
        info = json.loads((OUT / preset / solver / "run.json").read_text())
        res[f"{solver}_wall_time_s"] = info["wall_time_s"]
        res[f"{solver}_steps"] = info["steps"]
        res[f"{solver}_points"] = info["n_points"]
    m, c = ds["mpm"], ds["column"]
    y = m["y"].values
    for t in [t for t in TIMES if t <= end]:
        i = int(np.argmin(np.abs(m["time"].values - t)))
        j = int(np.argmin(np.abs(c["time"].values - t)))
        um, uc = m["velocity_x"].values[i], c["velocity_x"].values[j]
        fm, fc = m["phi_small"].values[i], c["phi_small"].values[j]
        ok = np.isfinite(um) & np.isfinite(uc)
        usm, usc = surface_velocity(y[ok], um[ok]), surface_velocity(y[ok], uc[ok])
        res["per_time"][f"{t:g}"] = {
            "u_surface_mpm": usm,
            "u_surface_column": usc,
            "u_surface_rel_diff": (usc - usm) / usm,
            "u_rms_over_u_s": float(np.sqrt(np.mean((uc[ok] - um[ok]) ** 2)) / usm),
            "phi_rms": float(np.sqrt(np.mean((fc[ok] - fm[ok]) ** 2))),
            "bins": int(ok.sum()),
        }
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", nargs="+", default=["chute_nonlocal", "chute_seed"])
    ap.add_argument("--end", type=float, default=20.0)
    a = ap.parse_args()
    OUT.mkdir(parents=True, exist_ok=True)
    results = [compare(p, a.end) for p in a.presets]
    (OUT / "summary.json").write_text(json.dumps(results, indent=2))
    lines = ["| preset | t (s) | u_s MPM / column (m/s) | Δu_s | u RMS / u_s | φ_s RMS |",
             "|---|---|---|---|---|---|"]  # fmt: skip
    for r in results:
        for t, v in r["per_time"].items():
            lines.append(f"| {r['preset']} | {t} | {v['u_surface_mpm']:.4f} / "
                         f"{v['u_surface_column']:.4f} | {100 * v['u_surface_rel_diff']:+.2f} % | "
                         f"{v['u_rms_over_u_s']:.4f} | {v['phi_rms']:.4f} |")  # fmt: skip
    lines.append("")
    for r in results:
        lines.append(f"{r['preset']}: MPM {r['mpm_steps']} steps of {r['mpm_points']} points in "
                     f"{r['mpm_wall_time_s']:.1f} s; column {r['column_steps']} steps of "
                     f"{r['column_points']} elements in {r['column_wall_time_s']:.1f} s (one "
                     "thread, loop time without compilation)")  # fmt: skip
    (OUT / "summary.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
