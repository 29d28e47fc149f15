"""The peer of ``segmpm bench``: Taichi's classic 2-D MLS-MPM fluid step ("mpm88") on the CPU.

The algorithm of Hu et al. (2018, *ACM TOG* 37, 150) as in Taichi's ``mpm88`` example: quadratic
B-splines, an APIC/MLS transfer, a weakly compressible fluid with pressure −E (J − 1), gravity and
separating box walls, one P2G, grid update and G2P per step. Written here against the Taichi
API (not copied), with particles at about four per cell in a square block of the unit box so that
N particles can be set freely.

One case per process (Taichi's thread count is fixed at ``ti.init``)::

    python -m segmpm.bench_taichi --n 32000 --threads 2 --steps 400 --repeats 5

prints one JSON line: particle-steps per second, ns per particle-step, first-call seconds. With
``--serve`` the process compiles and warms up, prints a JSON line, then times one block of
``--steps`` steps for every line ``block`` read on standard input (one JSON line each) until
``quit``: ``segmpm bench`` uses this to interleave the peer's blocks with its own, so that both
are timed in the same minutes of a shared machine.
Needs the optional ``bench`` extra (``pip install -e ".[bench]"``).
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from collections.abc import Callable
from typing import Any


def summarize(n: int, steps: int, walls: list[float]) -> dict[str, Any]:
    """Throughput of the median and the best of timed blocks of ``steps`` steps of ``n`` points."""
    med = statistics.median(walls)
    best = min(walls)
    return {
        "steps": steps,
        "repeats": len(walls),
        "wall_s": med,
        "block_wall_s": walls,
        "particle_steps_per_s": steps * n / med,
        "ns_per_particle_step": med / (steps * n) * 1e9,
        "best_ns_per_particle_step": best / (steps * n) * 1e9,
    }


ORDERS = ("random", "sorted")


def initial_positions(n: int, side: float, order: str):
    """``n`` particle positions in the block [0.2, 0.2 + side]²: ``"random"`` (uniform random
    points in random memory order, as Taichi's mpm88 example) or ``"sorted"`` (a square lattice in
    row-major order, the memory order of segmpm's lattice, so that consecutive particles share
    cells as in segmpm's bench)."""
    import numpy as np

    if order == "random":
        rng = np.random.default_rng(0)
        return 0.2 + side * rng.random((n, 2))
    if order != "sorted":
        raise ValueError(f"order = {order!r}; allowed: {', '.join(ORDERS)}")
    m = math.ceil(math.sqrt(n))
    k = np.arange(n)
    return np.stack([0.2 + side * ((k % m) + 0.5) / m, 0.2 + side * ((k // m) + 0.5) / m], axis=1)


def setup3d(n: int, threads: int, steps: int) -> tuple[Callable[[], float], dict[str, Any]]:
    """The same MLS-MPM fluid step in 3-D (Taichi's ``mpm3d`` algorithm; 27-node stencil), with
    float64 and particles on a sorted lattice at 8 per cell in the block [0.2, 0.6]³ of the
    unit box: the peer of segmpm's 3-D step (benchmarks/engine3d.py)."""
    import numpy as np
    import taichi as ti

    ti.init(arch=ti.cpu, cpu_max_num_threads=threads, default_fp=ti.f64, random_seed=0,
            offline_cache=True, log_level=ti.ERROR)  # fmt: skip
    side = 0.4
    m = math.ceil(n ** (1.0 / 3.0))
    n = m**3
    n_grid = max(16, int(round(m / 2 / side)))
    dx = 1.0 / n_grid
    inv_dx = float(n_grid)
    dt = 1e-4 * 64 / n_grid
    p_vol = (dx * 0.5) ** 3
    p_mass = p_vol * 1.0
    gravity = 9.8
    bound = 3
    E = 400.0

    x = ti.Vector.field(3, float, n)
    v = ti.Vector.field(3, float, n)
    C = ti.Matrix.field(3, 3, float, n)
    J = ti.field(float, n)
    grid_v = ti.Vector.field(3, float, (n_grid, n_grid, n_grid))
    grid_m = ti.field(float, (n_grid, n_grid, n_grid))

    @ti.kernel
    def step():
        for i, j, k in grid_m:
            grid_v[i, j, k] = [0.0, 0.0, 0.0]
            grid_m[i, j, k] = 0.0
        for p in x:
            xp = x[p] * inv_dx
            base = int(xp - 0.5)
            fx = xp - base
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
            stress = -dt * 4.0 * E * p_vol * (J[p] - 1.0) * inv_dx * inv_dx
            affine = ti.Matrix.identity(float, 3) * stress + p_mass * C[p]
            for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
                off = ti.Vector([i, j, k])
                dpos = (off - fx) * dx
                weight = w[i][0] * w[j][1] * w[k][2]
                grid_v[base + off] += weight * (p_mass * v[p] + affine @ dpos)
                grid_m[base + off] += weight * p_mass
        for i, j, k in grid_m:
            if grid_m[i, j, k] > 0.0:
                grid_v[i, j, k] /= grid_m[i, j, k]
            grid_v[i, j, k][1] -= dt * gravity
            idx = ti.Vector([i, j, k])
            for d in ti.static(range(3)):
                if idx[d] < bound and grid_v[i, j, k][d] < 0.0:
                    grid_v[i, j, k][d] = 0.0
                if idx[d] > n_grid - bound and grid_v[i, j, k][d] > 0.0:
                    grid_v[i, j, k][d] = 0.0
        for p in x:
            xp = x[p] * inv_dx
            base = int(xp - 0.5)
            fx = xp - base
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
            new_v = ti.Vector.zero(float, 3)
            new_c = ti.Matrix.zero(float, 3, 3)
            for i, j, k in ti.static(ti.ndrange(3, 3, 3)):
                off = ti.Vector([i, j, k])
                dpos = (off - fx) * dx
                weight = w[i][0] * w[j][1] * w[k][2]
                gv = grid_v[base + off]
                new_v += weight * gv
                new_c += 4.0 * inv_dx * inv_dx * weight * gv.outer_product(dpos)
            v[p] = new_v
            x[p] += dt * v[p]
            J[p] *= 1.0 + dt * new_c.trace()
            C[p] = new_c

    kk = np.arange(n)
    pos = np.stack([0.2 + side * ((kk % m) + 0.5) / m, 0.2 + side * (((kk // m) % m) + 0.5) / m,
                    0.2 + side * ((kk // (m * m)) + 0.5) / m], axis=1)  # fmt: skip
    x.from_numpy(pos)
    v.from_numpy(np.zeros((n, 3)))
    J.from_numpy(np.ones(n))
    C.from_numpy(np.zeros((n, 3, 3)))
    t0 = time.perf_counter()
    step()
    ti.sync()
    first = time.perf_counter() - t0
    for _ in range(max(1, steps // 10)):
        step()
    ti.sync()

    def block() -> float:
        t0 = time.perf_counter()
        for _ in range(steps):
            step()
        ti.sync()
        return time.perf_counter() - t0

    facts = {"n_points": n, "threads": threads, "first_call_s": first, "n_grid": n_grid,
             "order": "sorted", "dimension": 3,
             "taichi": ti.__version__ if hasattr(ti, "__version__") else ""}  # fmt: skip
    return block, facts


def setup(
    n: int, threads: int, steps: int, order: str = "random", dim: int = 2
) -> tuple[Callable[[], float], dict[str, Any]]:
    """Build, compile and warm up the mpm88 case with ``n`` particles on ``threads`` CPU threads,
    the particles initially in ``order`` (``initial_positions``); ``dim = 3``: :func:`setup3d`.

    Returns a function that times one block of ``steps`` steps (seconds) and the case's facts
    (first-call seconds, grid size, Taichi version)."""
    if dim == 3:
        return setup3d(n, threads, steps)
    import numpy as np
    import taichi as ti

    ti.init(arch=ti.cpu, cpu_max_num_threads=threads, default_fp=ti.f64, random_seed=0,
            offline_cache=True, log_level=ti.ERROR)  # fmt: skip
    side = 0.4  # particles fill [0.2, 0.6]², about 4 per cell
    n_grid = max(16, int(round(math.sqrt(n / 4.0) / side)))
    dx = 1.0 / n_grid
    inv_dx = float(n_grid)
    dt = 1e-4 * 128 / n_grid
    p_vol = (dx * 0.5) ** 2
    p_mass = p_vol * 1.0
    gravity = 9.8
    bound = 3
    E = 400.0

    x = ti.Vector.field(2, float, n)
    v = ti.Vector.field(2, float, n)
    C = ti.Matrix.field(2, 2, float, n)
    J = ti.field(float, n)
    grid_v = ti.Vector.field(2, float, (n_grid, n_grid))
    grid_m = ti.field(float, (n_grid, n_grid))

    @ti.kernel
    def step():
        for i, j in grid_m:
            grid_v[i, j] = [0.0, 0.0]
            grid_m[i, j] = 0.0
        for p in x:
            xp = x[p] * inv_dx
            base = int(xp - 0.5)
            fx = xp - base
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
            stress = -dt * 4.0 * E * p_vol * (J[p] - 1.0) * inv_dx * inv_dx
            affine = ti.Matrix([[stress, 0.0], [0.0, stress]]) + p_mass * C[p]
            for i, j in ti.static(ti.ndrange(3, 3)):
                off = ti.Vector([i, j])
                dpos = (off - fx) * dx
                weight = w[i][0] * w[j][1]
                grid_v[base + off] += weight * (p_mass * v[p] + affine @ dpos)
                grid_m[base + off] += weight * p_mass
        for i, j in grid_m:
            if grid_m[i, j] > 0.0:
                grid_v[i, j] /= grid_m[i, j]
            grid_v[i, j][1] -= dt * gravity
            if i < bound and grid_v[i, j][0] < 0.0:
                grid_v[i, j][0] = 0.0
            if i > n_grid - bound and grid_v[i, j][0] > 0.0:
                grid_v[i, j][0] = 0.0
            if j < bound and grid_v[i, j][1] < 0.0:
                grid_v[i, j][1] = 0.0
            if j > n_grid - bound and grid_v[i, j][1] > 0.0:
                grid_v[i, j][1] = 0.0
        for p in x:
            xp = x[p] * inv_dx
            base = int(xp - 0.5)
            fx = xp - base
            w = [0.5 * (1.5 - fx) ** 2, 0.75 - (fx - 1.0) ** 2, 0.5 * (fx - 0.5) ** 2]
            new_v = ti.Vector.zero(float, 2)
            new_c = ti.Matrix.zero(float, 2, 2)
            for i, j in ti.static(ti.ndrange(3, 3)):
                off = ti.Vector([i, j])
                dpos = (off - fx) * dx
                weight = w[i][0] * w[j][1]
                gv = grid_v[base + off]
                new_v += weight * gv
                new_c += 4.0 * inv_dx * inv_dx * weight * gv.outer_product(dpos)
            v[p] = new_v
            x[p] += dt * v[p]
            J[p] *= 1.0 + dt * new_c.trace()
            C[p] = new_c

    x.from_numpy(initial_positions(n, side, order))
    v.from_numpy(np.zeros((n, 2)))
    J.from_numpy(np.ones(n))
    C.from_numpy(np.zeros((n, 2, 2)))
    t0 = time.perf_counter()
    step()
    ti.sync()
    first = time.perf_counter() - t0
    for _ in range(max(1, steps // 10)):
        step()
    ti.sync()

    def block() -> float:
        t0 = time.perf_counter()
        for _ in range(steps):
            step()
        ti.sync()
        return time.perf_counter() - t0

    facts = {
        "n_points": n,
        "threads": threads,
        "first_call_s": first,
        "n_grid": n_grid,
        "order": order,
        "taichi": ti.__version__ if hasattr(ti, "__version__") else "",
    }
    return block, facts


def run(
    n: int, threads: int, steps: int, repeats: int = 1, order: str = "random", dim: int = 2
) -> dict[str, Any]:
    """Time ``repeats`` blocks of ``steps`` mpm88 steps with ``n`` particles on ``threads`` CPU
    threads (median and best block, as ``segmpm.bench``)."""
    block, facts = setup(n, threads, steps, order, dim)
    walls = [block() for _ in range(max(1, repeats))]
    return {**facts, **summarize(facts["n_points"], steps, walls)}


def serve(n: int, threads: int, steps: int, order: str = "random", dim: int = 2) -> int:
    """The ``--serve`` loop: one timed block per ``block`` line on stdin, until ``quit``."""
    block, facts = setup(n, threads, steps, order, dim)
    print(json.dumps(facts), flush=True)
    while True:
        cmd = sys.stdin.readline().strip()
        if cmd in ("quit", ""):  # "" : end of input
            break
        if cmd != "block":
            print(json.dumps({"error": f"unknown command {cmd!r}"}), flush=True)
            return 2
        print(json.dumps({"wall_s": block()}), flush=True)
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, required=True)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--order", choices=ORDERS, default="random",
                    help="initial particle order: random (mpm88) or a sorted lattice (segmpm's)")  # fmt: skip
    ap.add_argument("--dim", type=int, choices=(2, 3), default=2,
                    help="2: mpm88; 3: the 3-D step (27-node stencil, sorted lattice)")  # fmt: skip
    ap.add_argument("--serve", action="store_true",
                    help="time one block per 'block' line on stdin (see the module docstring)")  # fmt: skip
    a = ap.parse_args(argv)
    if a.serve:
        return serve(a.n, a.threads, a.steps, a.order, a.dim)
    print(json.dumps(run(a.n, a.threads, a.steps, a.repeats, a.order, a.dim)), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
