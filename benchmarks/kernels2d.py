"""Where the 2-D step spends its time: ns per particle-step of every kernel of the step (sort,
P2G, image nodes, grid update, G2P, material law) of the engine with D = 2 (segmpm.engine), on
the seed chute (local model) with about 32k points (``--points``), one thread (``--threads``).

    python benchmarks/kernels2d.py --out benchmarks/results/kernels2d-<date>.json

Until 2026-12-07 it also timed the former plane-strain engine (segmpm.mpm), blocks of the two
interleaved (``git show 61df0f7:benchmarks/kernels2d.py``; the results files of 2026-12-03 to
2026-12-07 hold both columns). The 2-D A/B against the commit before the generic engine is
benchmarks/ab2d_identity.py.

Each kernel is called from Python once per step (after a warm-up that compiles it), so the sum
of the kernels is a little above the cost of the compiled loop (``advance``), also reported.
"""

from __future__ import annotations

import argparse
import json
import platform
import statistics
import sys
import time

import numba

from segmpm.bench import _config_for
from segmpm.engine.codegen import for_material
from segmpm.engine.setup import build


def generic(n_points: int, threads: int):
    cfg = _config_for(n_points, "local")
    st = build(cfg, 2, threads=threads)
    k = for_material(2, st.mat)
    P, G, prm, mat, clock, seg = st.points, st.grid, st.prm, st.mat, st.clock, st.seg
    k.advance(P, G, prm, mat, clock, seg, 1e9, 100)
    nslabs = G.slab_start.shape[0] - 1
    nt = G.bounds.shape[0] - 1
    planes = k.image_planes(prm)
    dt = float(clock[0]["dt"])
    calls = {
        "sort": lambda: k.counting_sort(P.cursor, G.slab_start, G.order, nt),
        "p2g": lambda: k.p2g(P, G, prm, False),
        "images": lambda: (k.fold_images(G, planes, prm, 1.0), k.mirror_images(G, planes)),
        "grid_update": lambda: k.grid_update(G, prm, dt, 1.0),
        "g2p": lambda: k.g2p(P, G, prm, dt, nslabs),
        "material": lambda: k.update_stress(P, mat, dt, False, nt),
        "advance": lambda: k.advance(P, G, prm, mat, clock, seg, 1e9, 1),
    }  # fmt: skip
    return st.n, calls


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=32000)
    ap.add_argument("--steps", type=int, default=100, help="calls per kernel and block")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    numba.set_num_threads(args.threads)
    engines = {"generic": generic(args.points, args.threads)}
    times: dict[str, dict[str, list[float]]] = {e: {} for e in engines}
    for _n, calls in engines.values():  # warm-up: compile every kernel called from Python
        for f in calls.values():
            f()
    for _ in range(args.repeats):
        for e, (n, calls) in engines.items():
            for name, f in calls.items():
                t0 = time.perf_counter()
                for _ in range(args.steps):
                    f()
                dt = time.perf_counter() - t0
                times[e].setdefault(name, []).append(dt / (args.steps * n) * 1e9)
    res = {"command": " ".join(sys.argv), "machine": platform.processor() or platform.machine(),
           "threads": args.threads, "numba": numba.__version__,
           "points": {e: engines[e][0] for e in engines}, "ns_per_particle_step": {}}  # fmt: skip
    print(f"{'kernel':>12} {'ns per particle-step':>21}")
    for name in engines["generic"][1]:
        b = statistics.median(times["generic"][name])
        res["ns_per_particle_step"][name] = {"generic": b}
        print(f"{name:>12} {b:21.1f}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
