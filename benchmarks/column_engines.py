"""The column model (``scenario.solver = "column"``) on the production engine against the
dimension-generic one (``grid.engine = "generic"``): wall seconds per simulated second, in
interleaved rounds within one process (both warm), one thread, for the seed (local) and the
nonlocal presets, and the two engines' profiles compared at the end (the same physics to
round-off, with equal step counts); and, with ``--cold``, the cold compile of each engine's column for the
nonlocal preset, each in a fresh process with an empty kernel cache, one after the other.
Writes JSON progressively to ``--out``:

    python benchmarks/column_engines.py --rounds 7 --t 0.3 --cold \\
        --out benchmarks/results/column-engines-2026-12-07.json
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PRESETS = ("chute_seed", "chute_nonlocal")
ENGINES = ("production", "generic")
COLD = """
import json, sys, time
t0 = time.perf_counter()
from segmpm.config import load_config
from segmpm.simulation import Simulation
cfg = load_config(preset=sys.argv[1], overrides=["scenario.solver='column'",
    "grid.engine='" + sys.argv[2] + "'", "output.fields=false", "output.progress=false"])
sim = Simulation(cfg)
sim.threads = 1
t1 = time.perf_counter()
sim.advance(1.0, 1)
print(json.dumps({"setup_s": round(t1 - t0, 1), "first_call_s": round(time.perf_counter() - t1, 1)}))
"""


def _sim(preset: str, engine: str):
    from segmpm.config import load_config
    from segmpm.simulation import Simulation

    over = ["scenario.solver='column'", f"grid.engine='{engine}'", "output.fields=false",
            "output.progress=false"]  # fmt: skip
    sim = Simulation(load_config(preset=preset, overrides=over))
    sim.threads = 1
    return sim


def _steal() -> int:
    """Steal jiffies of the machine so far (/proc/stat), to say whether it was quiet."""
    try:
        return int(Path("/proc/stat").read_text().split("\n")[0].split()[8])
    except (OSError, IndexError, ValueError):
        return -1


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--t", type=float, default=0.3, help="simulated seconds per round")
    ap.add_argument("--cold", action="store_true", help="also time the cold compiles")
    ap.add_argument("--out", type=Path, required=True)
    a = ap.parse_args()
    res: dict = {"date": time.strftime("%Y-%m-%d %H:%M"), "rounds": a.rounds, "t": a.t,
                 "threads": 1, "steal_start": _steal(), "warm": {}, "cold": {}}  # fmt: skip

    def save() -> None:
        tmp = a.out.with_suffix(".tmp")
        tmp.write_text(json.dumps(res, indent=1))
        os.replace(tmp, a.out)

    sims = {(p, e): _sim(p, e) for p in PRESETS for e in ENGINES}
    for s in sims.values():  # compile and leave the start-up transient
        s.advance_to(0.05)
    for r in range(a.rounds):
        for p in PRESETS:
            order = ENGINES if r % 2 == 0 else ENGINES[::-1]
            for e in order:
                s = sims[(p, e)]
                n0, t0 = s.steps, time.perf_counter()
                s.advance_to(s.time + a.t)
                wall = time.perf_counter() - t0
                d = res["warm"].setdefault(f"{p}/{e}", {"wall_per_sim_s": [], "steps": []})
                d["wall_per_sim_s"].append(round(wall / a.t, 4))
                d["steps"].append(s.steps - n0)
            g, q = res["warm"][f"{p}/generic"], res["warm"][f"{p}/production"]
            ratios = [x / y for x, y in zip(g["wall_per_sim_s"], q["wall_per_sim_s"], strict=True)]
            res.setdefault("ratio_generic_over_production", {})[p] = {
                "per_round": [round(x, 3) for x in ratios],
                "median": round(statistics.median(ratios), 3)}  # fmt: skip
        res["steal_end"] = _steal()
        save()
    import numpy as np

    for p in PRESETS:  # the same physics: both engines at the same time, after every round
        pa, pg = sims[(p, "production")].profiles(), sims[(p, "generic")].profiles()
        us = float(np.nanmax(np.abs(pa["velocity_x"])))
        res.setdefault("identity", {})[p] = {
            "time": sims[(p, "production")].time, "u_s": us,
            "steps_equal": sims[(p, "production")].steps == sims[(p, "generic")].steps,
            "max_du_over_us": float(np.nanmax(np.abs(pg["velocity_x"] - pa["velocity_x"]))) / us,
            "max_dphi": float(np.nanmax(np.abs(pg["phi_small"] - pa["phi_small"]))),
            "max_dfluidity_rel": float(np.nanmax(np.abs(pg["fluidity"] - pa["fluidity"]))
                                       / np.nanmax(np.abs(pa["fluidity"])))}  # fmt: skip
    save()
    if a.cold:
        for e in ENGINES:
            with tempfile.TemporaryDirectory() as cache:
                env = {**os.environ, "SEGMPM_CACHE_DIR": cache}
                t0 = time.perf_counter()
                out = subprocess.run([sys.executable, "-c", COLD, "chute_nonlocal", e], env=env,
                                     capture_output=True, text=True, check=True)  # fmt: skip
                res["cold"][f"chute_nonlocal/{e}"] = {
                    **json.loads(out.stdout.strip().splitlines()[-1]),
                    "process_s": round(time.perf_counter() - t0, 1)}  # fmt: skip
            res["steal_end"] = _steal()
            save()
    print(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
