"""One engine, 2-D: the seed chute on the production plane-strain engine against the same
configuration on the dimension-generic engine (``grid.engine = "generic"``, the kernels of the 3-D
runs with D = 2), for the seed's local μ(I) model and the default, grain-calibrated nonlocal model
(docs/architecture.md, "One engine: where 2-D stands").

The two engines compute the same formulas in another order, so their states part at round-off,
and in a flowing granular layer a difference can grow. The question is how far the generic
engine's profiles are from the production ones over the whole 20 s, next to their distance from
the DEM. Reads the runs written by

    segmpm run chute_seed --out validation/results/engine2d/local_production <COMMON> \
        --set grid.engine='"production"'
    segmpm run chute_seed --out validation/results/engine2d/local_generic <COMMON> \
        --set grid.engine='"generic"'
    segmpm run --out validation/results/engine2d/nonlocal_production <COMMON> \
        --set grid.engine='"production"'
    segmpm run --out validation/results/engine2d/nonlocal_generic <COMMON> \
        --set grid.engine='"generic"'

(chute_seed: the seed's local μ(I) model; no preset: the default, grain-calibrated nonlocal model;
COMMON = --set output.fields=false --set grid.threads=1; see the log files beside them), and writes
validation/results/engine2d/summary.json:

    python validation/engine2d.py

Per output time and preset: the surface speed u_s of both engines, the largest and the RMS
difference of u(y) relative to u_s and of φ_s(y), and each engine's ``segmpm compare`` figures
against the DEM reference (validation/dem/reference_profiles.csv).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from segmpm.analysis.compare import compare_time, read_reference, read_run, surface_velocity

HERE = Path(__file__).resolve().parent
OUT = HERE / "results" / "engine2d"
DEM = HERE / "dem" / "reference_profiles.csv"


def _finite(a: np.ndarray) -> np.ndarray:
    return a[np.isfinite(a)]


def difference(a, b, t: float) -> dict[str, float]:
    """u_s of both runs and their profile differences at time t (bins defined in both)."""
    ia, ib = a.index(t), b.index(t)
    if abs(a.time[ia] - t) > 1e-9 or abs(b.time[ib] - t) > 1e-9:
        raise SystemExit(f"time {t} is missing from {a.path} or {b.path}")
    n = min(a.y.size, b.y.size)
    if not np.allclose(a.y[:n], b.y[:n]):
        raise SystemExit("the two runs have different profile bins")
    ua, ub = a.u[ia, :n], b.u[ib, :n]
    pa, pb = a.phi[ia, :n], b.phi[ib, :n]
    us = surface_velocity(a.y[:n], ua)
    du = _finite(ub - ua) / us if us > 0 else np.zeros(0)
    dp = _finite(pb - pa)
    both = np.isfinite(ua) & np.isfinite(ub)
    one = np.isfinite(ua) ^ np.isfinite(ub)
    return {
        "u_s_production": us,
        "u_s_generic": surface_velocity(b.y[:n], ub),
        "du_max_over_us": float(np.max(np.abs(du))) if du.size else math.nan,
        "du_rms_over_us": float(np.sqrt(np.mean(du**2))) if du.size else math.nan,
        "dphi_max": float(np.max(np.abs(dp))) if dp.size else math.nan,
        "dphi_rms": float(np.sqrt(np.mean(dp**2))) if dp.size else math.nan,
        "bins_both": int(both.sum()),
        "bins_only_one": int(one.sum()),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--presets", nargs="+", default=["local", "nonlocal"])
    args = ap.parse_args()
    ref = read_reference(DEM)
    summary: dict[str, dict] = {}
    for preset in args.presets:
        prod = read_run(OUT / f"{preset}_production")
        gen = read_run(OUT / f"{preset}_generic")
        rows = {}
        for t in prod.time:
            if t <= 0 or np.min(np.abs(gen.time - t)) > 1e-9:
                continue
            row = difference(prod, gen, float(t))
            if np.min(np.abs(ref.times() - t)) <= 1e-6:
                for name, run in (("production", prod), ("generic", gen)):
                    c = compare_time(run, ref, float(t), 0.0)
                    row[f"dem_{name}"] = {k: c[k] for k in c if k != "time"}
            rows[f"{t:g}"] = row
        runs = {}
        for name in ("production", "generic"):
            info = json.loads((OUT / f"{preset}_{name}" / "run.json").read_text())
            runs[name] = {k: info.get(k) for k in ("status", "time", "steps", "n_points",
                                                   "wall_time_s", "particle_steps_per_s")}  # fmt: skip
        summary[preset] = {"runs": runs, "times": rows}
        for t, r in rows.items():
            print(f"{preset:>9} t={t:>4}: u_s {r['u_s_production']:.4f} / {r['u_s_generic']:.4f}"
                  f"  max|du|/u_s {r['du_max_over_us']:.2e}  rms {r['du_rms_over_us']:.2e}"
                  f"  max|dphi| {r['dphi_max']:.2e}")  # fmt: skip
    OUT.mkdir(parents=True, exist_ok=True)
    (OUT / "summary.json").write_text(json.dumps(summary, indent=1, default=float) + "\n")


if __name__ == "__main__":
    main()
