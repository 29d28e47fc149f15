"""``segmpm bench``: throughput of the full coupled step on the seed chute.

For each size N (material points) and thread count, the seed chute case (granular model, sidewall
friction, segregation subcycle) is built with a periodic length that gives about N points, run for
a short settling period, then timed over ``repeats`` blocks of a fixed number of steps. Compile
time (first call) is reported apart. Results: particle-steps per second and ns per particle-step
of the median block (the best block and every block are in the JSON): on a shared virtual
machine single blocks vary by tens of per cent, and the median of several is what repeats.
"""

from __future__ import annotations

import importlib.util
import json
import platform
import subprocess
import sys
import time
from typing import Any

import numba

from . import __version__
from .bench_taichi import summarize
from .config import load_config
from .io.atomic import write_json


def _config_for(n_points: int):
    base = load_config(overrides=["output.progress=false", "output.fields=false"])
    h = base.grid.cell_size
    ppc = base.grid.particles_per_cell
    rows = round(base.geometry.depth / (h / ppc))
    cells = max(2, round(n_points / rows / ppc))
    # the production configuration: the concentration subcycle every segregation.dt = 1e-3 s,
    # i.e. about every 70 steps, so a few hundred timed steps include several of them
    return load_config(
        overrides=["output.progress=false", "output.fields=false", f"geometry.length={cells * h!r}"]
    )


def bench_case(n_points: int, threads: int, steps: int, repeats: int = 5) -> dict[str, Any]:
    """Time ``repeats`` blocks of ``steps`` steps of the seed chute with about ``n_points`` points
    on ``threads`` threads."""
    from .simulation import Simulation

    numba.set_num_threads(threads)
    cfg = _config_for(n_points)
    sim = Simulation(cfg)
    t0 = time.perf_counter()
    sim.advance(1.0, 1)  # compiles (or loads the cache)
    compile_s = time.perf_counter() - t0
    sim.advance(1.0, max(10, steps // 10))  # leave the start-up state
    walls = []
    for _ in range(max(1, repeats)):
        w0, s0 = sim.wall_time, sim.steps
        sim.advance(1.0, steps)
        if sim.steps - s0 != steps:
            raise RuntimeError(f"bench: the chute stopped after {sim.steps - s0} of {steps} steps")
        walls.append(sim.wall_time - w0)
    return {
        "n_points": sim.state.n,
        "threads": threads,
        **summarize(sim.state.n, steps, walls),
        "first_call_s": compile_s,
    }


def peer_case(n_points: int, threads: int, steps: int, repeats: int = 5) -> dict[str, Any] | None:
    """The Taichi mpm88 fluid step at the same N and thread count (``segmpm.bench_taichi``), in its
    own process; None if Taichi is not installed (the optional ``bench`` extra)."""
    if importlib.util.find_spec("taichi") is None:
        return None
    cmd = [sys.executable, "-m", "segmpm.bench_taichi", "--n", str(n_points),
           "--threads", str(threads), "--steps", str(steps), "--repeats", str(repeats)]  # fmt: skip
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=1800)
    lines = [ln for ln in out.stdout.splitlines() if ln.startswith("{")]
    if out.returncode != 0 or not lines:
        print(f"taichi peer failed: {out.stderr.strip()[-500:]}", file=sys.stderr)
        return None
    return json.loads(lines[-1])


def run_bench(
    sizes: list[int],
    threads: list[int],
    steps: int,
    json_out: str | None,
    peer: bool = True,
    repeats: int = 5,
) -> int:
    """Run the benchmark grid, print a table, optionally write JSON; returns the exit code.

    With ``peer`` (and Taichi installed) every case is followed by the Taichi mpm88 fluid step at
    the same N and thread count, and the ratio of the costs per particle-step is reported."""
    max_threads = numba.config.NUMBA_NUM_THREADS
    results = []
    print(f"segmpm {__version__} bench: seed chute (Fei model + sidewall + segregation), "
          f"median of {repeats} blocks of {steps} steps per case, numba {numba.__version__}, "
          f"up to {max_threads} threads")  # fmt: skip
    print(f"{'points':>8} {'threads':>7} {'Mpart-steps/s':>14} {'ns/part-step':>13} "
          f"{'first call s':>13} {'taichi ns':>10} {'ours/taichi':>11}")  # fmt: skip
    for n in sizes:
        for t in threads:
            if t > max_threads:
                print(
                    f"{n:>8} {t:>7}  skipped: only {max_threads} threads available", file=sys.stderr
                )
                continue
            r = bench_case(n, t, steps, repeats)
            q = peer_case(r["n_points"], t, steps, repeats) if peer else None
            if q is not None:
                r["taichi_mpm88"] = q
                r["cost_ratio_vs_taichi"] = r["ns_per_particle_step"] / q["ns_per_particle_step"]
            results.append(r)
            extra = (f"{q['ns_per_particle_step']:>10.1f} {r['cost_ratio_vs_taichi']:>11.2f}"
                     if q is not None else f"{'-':>10} {'-':>11}")  # fmt: skip
            print(f"{r['n_points']:>8} {t:>7} {r['particle_steps_per_s'] / 1e6:>14.3f} "
                  f"{r['ns_per_particle_step']:>13.1f} {r['first_call_s']:>13.2f} {extra}",
                  flush=True)  # fmt: skip
    doc = {
        "segmpm_version": __version__,
        "machine": {
            "python": platform.python_version(),
            "processor": platform.processor(),
            "numba": numba.__version__,
            "max_threads": max_threads,
        },  # fmt: skip
        "results": results,
    }
    if json_out:
        write_json(json_out, doc)
    return 0
