"""The default run's cost per step on the default (dimension-generic) engine against the former
production engine: the default preset (nonlocal) and the seed's local preset at their own
resolution (596 points, one thread), blocks of ``--block`` simulated seconds interleaved
A/B/A/B in one process, both runs continuing the same trajectory (the two engines agree to
round-off, so the blocks take the same steps).

    NUMBA_NUM_THREADS=1 python benchmarks/default_engines_ab.py --rounds 9 \\
        --out benchmarks/results/default-engines-ab-2026-12-07.json

Prints and writes the loop seconds per block and the per-round ratio generic / production
(median and quartiles), and the steal jiffies of /proc/stat over the run.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys

import numba

from segmpm.config import DEFAULT_PRESET, load_config
from segmpm.simulation import Simulation


def steal() -> int:
    with open("/proc/stat") as f:
        return int(f.readline().split()[8])


def make(preset: str, engine: str) -> Simulation:
    cfg = load_config(preset, [f"grid.engine='{engine}'", "grid.threads=1",
                               "output.progress=false"])  # fmt: skip
    sim = Simulation(cfg)
    sim.advance(sim.time, 0)  # compile or load the loop
    return sim


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rounds", type=int, default=9)
    ap.add_argument("--block", type=float, default=0.25, help="simulated seconds per block")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    numba.set_num_threads(1)
    s0 = steal()
    res: dict = {"command": " ".join(sys.argv), "machine": platform.processor() or platform.machine(),
                 "numba": numba.__version__, "cases": {}}  # fmt: skip
    for name, preset in (
        ("nonlocal (default)", DEFAULT_PRESET),
        ("local (chute_seed)", "chute_seed"),
    ):
        sims = {e: make(preset, e) for e in ("production", "auto")}
        blocks: dict[str, list[float]] = {e: [] for e in sims}
        steps: dict[str, list[int]] = {e: [] for e in sims}
        t = 0.0
        for _ in range(args.rounds):
            t += args.block
            for e, sim in sims.items():
                w0, n0 = sim.wall_time, sim.steps
                sim.advance_to(t)
                blocks[e].append(sim.wall_time - w0)
                steps[e].append(sim.steps - n0)
        ratios = sorted(b / a for a, b in zip(blocks["production"], blocks["auto"], strict=True))
        q = statistics.quantiles(ratios, n=4)
        case = {"points": sims["auto"].state.n, "steps_per_block": steps,
                "loop_s_per_block": blocks, "ratio_median": statistics.median(ratios),
                "ratio_quartiles": [q[0], q[2]]}  # fmt: skip
        res["cases"][name] = case
        us = {e: 1e6 * sum(blocks[e]) / sum(steps[e]) for e in sims}
        print(f"{name}: {case['points']} points, {sum(steps['auto'])} steps per engine; "
              f"µs/step production {us['production']:.2f}, generic {us['auto']:.2f}; "
              f"per-round ratio generic/production median {case['ratio_median']:.3f} "
              f"(IQR {q[0]:.3f}-{q[2]:.3f})")  # fmt: skip
    res["steal_jiffies"] = steal() - s0
    print(f"steal jiffies over the run: {res['steal_jiffies']}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
