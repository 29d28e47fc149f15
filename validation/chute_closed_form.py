"""Chute runs through the CLI against the closed forms (docs/model.md §3), for any settings.

Each case is ``segmpm run`` with ``--set`` overrides of slope, depth, width, sidewall friction and
stiffness scale (no segregation); the last profile of ``profiles.nc`` is compared with
``segmpm.analysis.closed_form``: surface velocity, flowing depth (where u > 2 % of the surface
velocity) and the velocity RMS over the surface velocity. Writes
validation/results/chute_closed_form.json. Usage::

    python validation/chute_closed_form.py                      # the built-in cases
    python validation/chute_closed_form.py --case 27 0.015 0.03 0.25 1e-2 --end 1.5
"""

from __future__ import annotations

import argparse
import json
import pathlib
import subprocess
import sys

import numpy as np
import xarray as xr

from segmpm.analysis.closed_form import bagnold_velocity, sidewall_velocity
from segmpm.config import load_config

OUT = pathlib.Path(__file__).parent / "results"

#: slope (deg), depth (m), width (m), μ_w, stiffness scale
CASES = [
    (24.5, 0.010, 0.022, 0.20, 1e-3),
    (27.0, 0.015, 0.030, 0.25, 1e-2),
    (29.0, 0.008, 0.022, 0.00, 1e-3),
    (26.0, 0.0373, 0.022, 0.30, 1e-3),
]


def run_case(theta, depth, width, mu_w, scale, end, cell) -> dict:
    tag = f"t{theta:g}_H{depth:g}_W{width:g}_mu{mu_w:g}_s{scale:g}"
    out = OUT / "chute_closed_form" / tag
    sets = [
        f"geometry.slope_deg={theta!r}", f"geometry.depth={depth!r}", f"geometry.width={width!r}",
        f"boundary.sidewall_friction={mu_w!r}", f"material.stiffness_scale={scale!r}",
        "segregation.model='none'", f"time.end={end!r}", f"output.profile_times=[0.0, {end!r}]",
        "output.fields=false", "output.figures=false", f"grid.cell_size={cell!r}",
        f"geometry.length={2 * cell!r}", f"output.profile_bin={cell / 2!r}",
    ]  # fmt: skip
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
    for s in sets:
        cmd += ["--set", s]
    subprocess.run(cmd, check=True)
    cfg = load_config(out / "config.toml")
    with xr.open_dataset(out / "profiles.nc", engine="h5netcdf") as ds:
        y = ds["y"].values
        u = ds["velocity_x"].values[-1]
    ok = np.isfinite(u)
    y, u = y[ok], u[ok]
    if mu_w > 0:
        th, zf = sidewall_velocity(cfg, y)
    else:
        th, zf = bagnold_velocity(cfg, y), depth
    us_th = float(th.max())

    def flowing_depth(v):
        moving = np.nonzero(v > 0.02 * v.max())[0]
        return float(depth - y[moving[0]]) if moving.size else 0.0

    return {
        "case": {
            "slope_deg": theta,
            "depth": depth,
            "width": width,
            "mu_w": mu_w,
            "stiffness_scale": scale,
            "end": end,
            "cell_size": cell,
        },  # fmt: skip
        "surface_velocity": float(u.max()),
        "surface_velocity_closed_form": us_th,
        "surface_error": float(u.max()) / us_th - 1.0,
        "flowing_depth": flowing_depth(u),
        "flowing_depth_closed_form": flowing_depth(th),
        "zeta_f": zf,
        "rms_over_surface": float(np.sqrt(np.mean((u - th) ** 2)) / us_th),
    }


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--case", type=float, nargs=5, action="append",
                    metavar=("SLOPE", "DEPTH", "WIDTH", "MU_W", "SCALE"))  # fmt: skip
    ap.add_argument("--end", type=float, default=2.0, help="simulated time to the steady state")
    ap.add_argument("--cell", type=float, default=5e-4)
    args = ap.parse_args()
    OUT.mkdir(exist_ok=True)
    results = []
    for c in args.case or CASES:
        r = run_case(*c, args.end, args.cell)
        results.append(r)
        print(f"{r['case']}: surface {100 * r['surface_error']:+.2f} %, flowing depth "
              f"{1e3 * r['flowing_depth']:.2f} vs {1e3 * r['flowing_depth_closed_form']:.2f} mm, "
              f"RMS {100 * r['rms_over_surface']:.2f} %", flush=True)  # fmt: skip
        (OUT / "chute_closed_form.json").write_text(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
