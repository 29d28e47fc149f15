"""Where the 2-D step spends its time, on each engine: ns per particle-step of every kernel of the
step (sort, P2G, image nodes, grid update, G2P, material law) of the production plane-strain
engine (segmpm.mpm) and of the dimension-generic engine with D = 2 (segmpm.engine), on the seed
chute (local model) with about 32k points (``--points``), one thread (``--threads``), blocks of the two engines interleaved.

    python benchmarks/kernels2d.py --out benchmarks/results/kernels2d-2026-12-03.json

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
from segmpm.mpm import step as S
from segmpm.mpm import transfer as T
from segmpm.mpm.params import G_GX, G_GY, S_DT
from segmpm.simulation import Simulation, _bounds


def production(n_points: int, threads: int):
    sim = Simulation(_config_for(n_points, "local"))
    sim.threads = threads
    sim.advance(1e9, 100)
    st, w = sim.state, sim.state.work
    bounds = _bounds(w)
    nt = bounds.shape[0] - 1
    images = T.image_pairs(st.gp, w["grid"].shape[0], w["grid"].shape[1])
    nstrips = w["strip_start"].shape[0] - 1
    dt = float(st.sc[S_DT])
    grid, gv = w["grid"], w["gv"]
    calls = {
        "sort": lambda: T.counting_sort(w["cursor"], w["strip_start"], w["order"], nt),
        "p2g": lambda: T.p2g(st.x, st.v, st.C, st.mass, st.vol0, st.J, st.sig, st.diag[0],
                             st.gp, grid, w["strip_start"], w["order"], bounds, True),
        "images": lambda: (T.fold_images(grid, images, st.gp[G_GX], st.gp[G_GY]),
                           T.mirror_images(gv, images)),
        "grid_update": lambda: T.grid_update(st.gp, grid, gv, dt, 1.0, True),
        "g2p": lambda: S.update_points(st.x, st.v, st.C, st.J, st.gp, gv, dt, w["flags"],
                                       w["cursor"], nstrips, w["lg"]),
        "material": lambda: S.update_stress(st.x, st.v, st.J, st.eps, st.sig, st.phi, st.gf,
                                            st.diag, st.s_int, st.g_int, st.mp, dt, w["flags"],
                                            w["lg"], False, nt),
        "advance": lambda: sim.advance(1e9, 1),
    }  # fmt: skip
    return st.n, calls


def generic(n_points: int, threads: int):
    cfg = _config_for(n_points, "generic-local")
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
    engines = {
        "production": production(args.points, args.threads),
        "generic": generic(args.points, args.threads),
    }
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
    print(f"{'kernel':>12} {'production':>11} {'generic':>9} {'ratio':>6}   (ns per particle-step)")
    for name in engines["production"][1]:
        a = statistics.median(times["production"][name])
        b = statistics.median(times["generic"][name])
        res["ns_per_particle_step"][name] = {"production": a, "generic": b, "ratio": b / a}
        print(f"{name:>12} {a:11.1f} {b:9.1f} {b / a:6.2f}")
    if args.out:
        with open(args.out, "w") as f:
            json.dump(res, f, indent=1)


if __name__ == "__main__":
    main()
