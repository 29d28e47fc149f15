"""Throughput of the 3-D coupled step (the generic engine): particle-steps per second of the
seed chute (local rheology) at 16k, 64k and 256k points, on the threads given.

    NUMBA_NUM_THREADS=2 python benchmarks/engine3d.py --threads 2 --peer \
        --out benchmarks/results/engine3d-2026-12-03.json

The point count is set by the channel width (mirror plane, h = 0.5 mm, 2 points per cell and
axis, 2 mm periodic length). Each size: a 20-step warm-up, then ``--repeats`` blocks of
``--steps`` steps; the median block is reported. With ``--peer`` the 64k case is interleaved
block by block with Taichi's 3-D MLS-MPM step in float64 on as many threads
(``python -m segmpm.bench_taichi --dim 3 --serve``, the ``bench`` extra), so that both are timed
in the same minutes of the machine: ``cost_ratio`` = segmpm's ns per particle-step over Taichi's.
The default step (local law, so ``grid.volumetric_smoothing = "auto"`` leaves the smoothing off)
is interleaved block by block with the same state built with ``"on"`` (as every 3-D run of the
nonlocal rheology has it): ``smoothing_cost`` is the ratio of their times, on over off.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import subprocess
import sys
import time

import numba

from segmpm.config import load_config
from segmpm.engine.codegen import for_material
from segmpm.engine.setup import build

#: modelled half-widths (m) giving about 16k, 64k, 256k points at h = 0.5 mm (depth 37.3 mm:
#: 8 × 149 points per 0.25 mm of width)
WIDTHS = {"16k": 0.0035, "64k": 0.0135, "256k": 0.054}


def _json_line(stream) -> dict:
    """The next JSON line of the peer (Taichi prints its banner on stdout first)."""
    while True:
        line = stream.readline()
        if not line:
            raise RuntimeError("the Taichi peer exited early")
        if line.lstrip().startswith("{"):
            return json.loads(line)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--sizes", nargs="+", default=list(WIDTHS))
    ap.add_argument("--out", default=None)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--peer", action="store_true", help="interleave Taichi's 3-D step at 64k")
    args = ap.parse_args()
    numba.set_num_threads(args.threads)
    rows = []
    for size in args.sizes:
        half = WIDTHS[size]
        common = ["material.rheology='local'", "segregation.model='none'",
                  "geometry.dimension=3", "geometry.mirror=true",
                  f"geometry.width={2 * half}", "geometry.length=0.002"]  # fmt: skip
        cfg = load_config(None, common, preset="chute_seed")
        st = build(cfg, 3, threads=args.threads)
        cfg_on = load_config(None, [*common, "grid.volumetric_smoothing='on'"],
                             preset="chute_seed")  # fmt: skip
        st_on = build(cfg_on, 3, threads=args.threads)
        assert st.prm["dilatation"][0] == 0 and st_on.prm["dilatation"][0] != 0
        k = for_material(3, st.mat)  # the local law: its step file
        for s_ in (st, st_on):
            k.advance(s_.points, s_.grid, s_.prm, s_.mat, s_.clock, s_.seg, 1e9, 20)
        peer = None
        if args.peer and size == "64k":
            peer = subprocess.Popen(
                [sys.executable, "-m", "segmpm.bench_taichi", "--dim", "3", "--serve", "--n",
                 str(st.n), "--threads", str(args.threads), "--steps", str(args.steps)],
                stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)  # fmt: skip
            facts = _json_line(peer.stdout)
        ours, theirs, on = [], [], []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            k.advance(st.points, st.grid, st.prm, st.mat, st.clock, st.seg, 1e9, args.steps)
            ours.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            k.advance(st_on.points, st_on.grid, st_on.prm, st_on.mat, st_on.clock,
                      st_on.seg, 1e9, args.steps)  # fmt: skip
            on.append(time.perf_counter() - t0)
            if peer is not None:
                peer.stdin.write("block\n")
                peer.stdin.flush()
                theirs.append(_json_line(peer.stdout)["wall_s"])
        el = statistics.median(ours)
        rate = st.n * args.steps / el
        row = {"size": size, "points": st.n, "steps": args.steps, "blocks_s": ours,
               "seconds": el, "particle_steps_per_s": rate,
               "ns_per_particle_step": el / (st.n * args.steps) * 1e9,
               "smoothing_on": {"blocks_s": on,
                                "particle_steps_per_s": st.n * args.steps / statistics.median(on)},
               "smoothing_cost": statistics.median(on) / el}  # fmt: skip
        if peer is not None:
            peer.stdin.write("quit\n")
            peer.stdin.flush()
            peer.wait(timeout=60)
            tm = statistics.median(theirs)
            row["taichi"] = {
                **facts,
                "blocks_s": theirs,
                "seconds": tm,
                "particle_steps_per_s": facts["n_points"] * args.steps / tm,
                "ns_per_particle_step": tm / (facts["n_points"] * args.steps) * 1e9,
            }
            row["cost_ratio"] = row["ns_per_particle_step"] / row["taichi"]["ns_per_particle_step"]
            print(
                f"       Taichi 3-D MLS-MPM f64: {row['taichi']['particle_steps_per_s']:.3g} "
                f"particle-steps/s ({facts['n_points']} points); cost ratio "
                f"{row['cost_ratio']:.2f}"
            )
        rows.append(row)
        print(
            f"{size:>5}: {st.n:7d} points, {rate:.3g} particle-steps/s on {args.threads} threads "
            f"(smoothing on: {row['smoothing_on']['particle_steps_per_s']:.3g})",
            flush=True,
        )
    base = rows[0]["particle_steps_per_s"]
    for r in rows:
        r["cost_vs_first"] = base / r["particle_steps_per_s"]
    res = {"threads": args.threads, "machine": platform.processor() or platform.machine(),
           "command": " ".join(sys.argv), "rows": rows,
           "growth_16k_to_256k": rows[-1]["cost_vs_first"] if len(rows) > 1 else None}  # fmt: skip
    if args.out:
        with open(args.out, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
