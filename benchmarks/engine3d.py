"""Throughput of the 3-D coupled step (the generic engine): particle-steps per second of the
seed chute (local rheology) at 16k, 64k and 256k points, on the threads given.

    NUMBA_NUM_THREADS=2 python benchmarks/engine3d.py --threads 2 --out benchmarks/results/engine3d.json

The point count is set by the channel width (mirror plane, h = 0.5 mm, 2 points per cell and
axis, 2 mm periodic length). Each size: a 20-step warm-up, then ``--steps`` steps timed.
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numba

from segmpm.config import load_config
from segmpm.engine.codegen import kernels
from segmpm.engine.setup import build

#: modelled half-widths (m) giving about 16k, 64k, 256k points at h = 0.5 mm (depth 37.3 mm:
#: 8 × 149 points per 0.25 mm of width)
WIDTHS = {"16k": 0.0035, "64k": 0.0135, "256k": 0.054}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--sizes", nargs="+", default=list(WIDTHS))
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    numba.set_num_threads(args.threads)
    k = kernels(3)
    rows = []
    for size in args.sizes:
        half = WIDTHS[size]
        cfg = load_config(None, ["material.rheology='local'", "segregation.model='none'",
                                 "geometry.dimension=3", "geometry.mirror=true",
                                 f"geometry.width={2 * half}", "geometry.length=0.002"],
                          preset="chute_seed")  # fmt: skip
        st = build(cfg, 3, threads=args.threads)
        k.advance(st.points, st.grid, st.prm, st.mat, st.clock, st.seg, 1e9, 20)
        t0 = time.perf_counter()
        k.advance(st.points, st.grid, st.prm, st.mat, st.clock, st.seg, 1e9, args.steps)
        el = time.perf_counter() - t0
        rate = st.n * args.steps / el
        rows.append({"size": size, "points": st.n, "steps": args.steps, "seconds": el,
                     "particle_steps_per_s": rate})  # fmt: skip
        print(f"{size:>5}: {st.n:7d} points, {rate:.3g} particle-steps/s on {args.threads} threads")
    base = rows[0]["particle_steps_per_s"]
    for r in rows:
        r["cost_vs_first"] = base / r["particle_steps_per_s"]
    res = {"threads": args.threads, "machine": platform.processor() or platform.machine(),
           "rows": rows}  # fmt: skip
    if args.out:
        with open(args.out, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
