"""Courant-number study of the seed chute (the evidence for the default preset's CFL = 0.5).

Runs the default configuration to ``--end`` (1 s) at several Courant numbers and compares the
depth profiles with the smallest one: velocity RMS (over the surface velocity), the largest φ_s
and pressure differences, and the number of steps. Writes validation/results/cfl_study.json.
Usage: python validation/cfl_study.py [--end 1.0] [--cfl 0.25 0.4 0.5 0.6]
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time

import numpy as np

from segmpm.config import load_config
from segmpm.simulation import Simulation

OUT = pathlib.Path(__file__).parent / "results"


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--end", type=float, default=1.0)
    ap.add_argument("--cfl", type=float, nargs="+", default=[0.25, 0.4, 0.5, 0.6])
    args = ap.parse_args()
    runs = {}
    for cfl in sorted(args.cfl):
        cfg = load_config(preset="chute_seed", overrides=["output.progress=false", "output.fields=false",
                                     f"time.cfl={cfl!r}"])  # fmt: skip
        sim = Simulation(cfg)
        t0 = time.perf_counter()
        sim.advance_to(args.end)
        runs[cfl] = (sim.profiles(), sim.steps, time.perf_counter() - t0)
        print(f"CFL {cfl}: {sim.steps} steps, {runs[cfl][2]:.1f} s", flush=True)
    ref_cfl = min(runs)
    ref = runs[ref_cfl][0]
    us = float(np.nanmax(ref["velocity_x"]))
    pmax = float(np.nanmax(ref["pressure"]))
    summary = {"end": args.end, "reference_cfl": ref_cfl, "per_cfl": {}}
    for cfl, (p, steps, wall) in runs.items():
        ok = np.isfinite(p["velocity_x"]) & np.isfinite(ref["velocity_x"])
        du = p["velocity_x"][ok] - ref["velocity_x"][ok]
        summary["per_cfl"][f"{cfl:g}"] = {
            "steps": steps,
            "wall_s": wall,
            "surface_velocity": float(np.nanmax(p["velocity_x"])),
            "rms_du_over_us": float(np.sqrt(np.mean(du**2)) / us),
            "max_abs_dphi": float(np.nanmax(np.abs(p["phi_small"] - ref["phi_small"]))),
            "max_dp_over_pmax": float(np.nanmax(np.abs(p["pressure"] - ref["pressure"])) / pmax),
        }
    OUT.mkdir(exist_ok=True)
    (OUT / "cfl_study.json").write_text(json.dumps(summary, indent=2))
    print(json.dumps(summary, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
