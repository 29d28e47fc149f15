"""Resolution convergence of the 3-D seed chute with resolved walls over its first 2 s: the runs
walls3d_h1mm (h = 1 mm) and walls3d_h0.79mm (h = 11/14 mm, the next cell size that divides the
11 mm half-width) of validation/results/sidewall3d (commands in their logs and config.toml).
Prints and writes validation/results/sidewall3d/convergence.json: surface speed, flowing depth
and the RMS difference of the width-averaged velocity profiles (relative to the surface speed).

    python validation/sidewall3d_convergence.py
"""

from __future__ import annotations

import json
import pathlib

import numpy as np
import xarray as xr
from sidewall3d import flowing_depth, surface_speed  # noqa: I001  (same folder)

RES = pathlib.Path(__file__).parent / "results" / "sidewall3d"
RUNS = {"h=1mm": "walls3d_h1mm", "h=0.786mm": "walls3d_h0.79mm"}


def main() -> None:
    data = {k: xr.open_dataset(RES / d / "profiles.nc").load() for k, d in RUNS.items()}
    out = []
    for t in (0.5, 1.0, 2.0):
        row: dict = {"time": t}
        prof = {}
        for k, ds in data.items():
            y = ds.y.values
            u = ds.velocity_x.sel(time=t).values
            f = ds.solid_fraction.sel(time=t).values
            us, top = surface_speed(y, u, f)
            row[k] = {"surface_speed": us, "flowing_depth": flowing_depth(y, u, top, us)}
            prof[k] = (y, u)
        (ya, ua), (yb, ub) = prof["h=1mm"], prof["h=0.786mm"]
        grid = np.arange(0.0005, 0.036, 0.0005)
        da = np.interp(grid, ya[np.isfinite(ua)], ua[np.isfinite(ua)])
        db = np.interp(grid, yb[np.isfinite(ub)], ub[np.isfinite(ub)])
        row["velocity_rms_over_us"] = float(
            np.sqrt(np.mean((da - db) ** 2)) / row["h=0.786mm"]["surface_speed"]
        )
        row["surface_speed_change"] = (
            row["h=0.786mm"]["surface_speed"] / row["h=1mm"]["surface_speed"] - 1.0
        )
        out.append(row)
        print(json.dumps(row))
    (RES / "convergence.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
