r"""Resolution convergence of the 3-D seed chute with resolved walls over its first 2 s, between a
run at h = 1 mm and one at h = 11/14 mm (the next cell size that divides the 11 mm half-width) of
validation/results/sidewall3d. Prints and writes validation/results/sidewall3d/convergence*.json:
surface speed, flowing depth and the RMS difference of the width-averaged velocity profiles
(relative to the surface speed).

The local model of §4 (walls3d_h1mm, walls3d_h0.79mm; commands in their logs and config.toml):

    python validation/sidewall3d_convergence.py

The default model's 3-D case at its lattice of 2 points per cell downslope and 3 across
(examples/chute_nonlocal_3d.toml; the h = 1 mm run is the 5 s run circ_ppc233_mirror_h1mm of
validation/sidewall3d_circulation.py):

    segmpm run examples/chute_nonlocal_3d.toml --out validation/results/sidewall3d/nl233_h0.79mm \
        --set grid.cell_size=0.0007857142857142857 --set geometry.length=0.0015714285714285715 \
        --set time.end=2 --set grid.threads=2 --set output.fields=false
    python validation/sidewall3d_convergence.py --coarse circ_ppc233_mirror_h1mm \
        --fine nl233_h0.79mm --tag nl233
"""

from __future__ import annotations

import argparse
import json
import pathlib

import numpy as np
import xarray as xr
from sidewall3d import flowing_depth, surface_speed  # noqa: I001  (same folder)

RES = pathlib.Path(__file__).parent / "results" / "sidewall3d"


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--coarse", default="walls3d_h1mm", help="the h = 1 mm run")
    ap.add_argument("--fine", default="walls3d_h0.79mm", help="the h = 11/14 mm run")
    ap.add_argument("--tag", default="", help="write convergence_TAG.json")
    args = ap.parse_args()
    runs = {"h=1mm": args.coarse, "h=0.786mm": args.fine}
    data = {k: xr.open_dataset(RES / d / "profiles.nc").load() for k, d in runs.items()}
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
    name = f"convergence_{args.tag}.json" if args.tag else "convergence.json"
    out = {"coarse": args.coarse, "fine": args.fine, "rows": out} if args.tag else out
    (RES / name).write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
