"""``segmpm bench``: throughput of the full coupled step on the seed chute.

For each size N (material points) the seed chute case (granular model, sidewall friction,
segregation subcycle) is built with a periodic length that gives about N points, compiled (the
first call, reported apart), run for a short settling period, then timed over ``repeats`` rounds.
Each round times one block of ``steps`` steps at every thread count and, with the peer, one block
of the Taichi mpm88 fluid step at the same N and thread count right after ours. Costs are the
median block; the ratios (speed-up over one thread, cost against the peer) are the medians of
the ratios within each round: on a shared virtual machine the speed of the whole machine drifts
by tens of per cent from minute to minute, and a ratio of blocks timed seconds apart is what
repeats. The best block and every block are in the JSON.
"""

from __future__ import annotations

import importlib.util
import json
import platform
import statistics
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


class Peer:
    """The Taichi mpm88 peer at one N and thread count, in its own process
    (``python -m segmpm.bench_taichi --serve``), timing one block per :meth:`block` call."""

    def __init__(self, n_points: int, threads: int, steps: int):
        cmd = [sys.executable, "-m", "segmpm.bench_taichi", "--serve", "--n", str(n_points),
               "--threads", str(threads), "--steps", str(steps)]  # fmt: skip
        self.proc = subprocess.Popen(
            cmd, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
        )
        self.facts = self._reply()

    def _reply(self) -> dict[str, Any]:
        while True:
            line = self.proc.stdout.readline()
            if not line:
                err = self.proc.stderr.read().strip()[-500:]
                raise RuntimeError(f"the taichi peer stopped: {err}")
            if line.startswith("{"):
                return json.loads(line)

    def block(self) -> float:
        """Wall seconds of one timed block."""
        self.proc.stdin.write("block\n")
        self.proc.stdin.flush()
        return float(self._reply()["wall_s"])

    def close(self) -> None:
        if self.proc.poll() is None:
            try:
                self.proc.stdin.write("quit\n")
                self.proc.stdin.flush()
                self.proc.wait(timeout=60)
            except (OSError, subprocess.TimeoutExpired):
                self.proc.kill()


def _peers(n: int, threads: list[int], steps: int) -> dict[int, Peer]:
    """One peer per thread count; empty if Taichi is not installed or a peer fails to start."""
    if importlib.util.find_spec("taichi") is None:
        return {}
    peers: dict[int, Peer] = {}
    try:
        for t in threads:
            peers[t] = Peer(n, t, steps)
    except RuntimeError as err:
        print(f"taichi peer failed: {err}", file=sys.stderr)
        for q in peers.values():
            q.close()
        return {}
    return peers


def _paired(num: list[float], den: list[float]) -> float:
    """Median over rounds of num[r] / den[r]."""
    return statistics.median(a / b for a, b in zip(num, den, strict=True))


def bench_size(
    n_points: int, threads: list[int], steps: int, repeats: int = 5, peer: bool = True
) -> list[dict[str, Any]]:
    """Time the seed chute with about ``n_points`` points at every thread count in ``threads``
    (and the Taichi peer if ``peer``), their blocks interleaved round by round; one result per
    thread count."""
    from .simulation import Simulation

    sim = Simulation(_config_for(n_points))
    n = sim.state.n
    first: dict[int, float] = {}
    for t in threads:
        numba.set_num_threads(t)
        t0 = time.perf_counter()
        sim.advance(1.0, 1)  # compiles (or loads the cache) on the first thread count
        first[t] = time.perf_counter() - t0
    sim.advance(1.0, max(10, steps // 10))  # leave the start-up state
    peers = _peers(n, threads, steps) if peer else {}
    walls: dict[int, list[float]] = {t: [] for t in threads}
    pwalls: dict[int, list[float]] = {t: [] for t in peers}
    try:
        for _ in range(max(1, repeats)):
            for t in threads:
                numba.set_num_threads(t)
                w0, s0 = sim.wall_time, sim.steps
                sim.advance(1.0, steps)
                if sim.steps - s0 != steps:
                    raise RuntimeError(
                        f"bench: the chute stopped after {sim.steps - s0} of {steps} steps"
                    )
                walls[t].append(sim.wall_time - w0)
                if t in peers:
                    pwalls[t].append(peers[t].block())
    finally:
        for q in peers.values():
            q.close()
    out = []
    for t in threads:
        r: dict[str, Any] = {"n_points": n, "threads": t, **summarize(n, steps, walls[t]),
                             "first_call_s": first[t]}  # fmt: skip
        if t != threads[0]:
            r[f"speedup_vs_{threads[0]}_threads"] = _paired(walls[threads[0]], walls[t])
        if t in peers:
            q = {**peers[t].facts, **summarize(n, steps, pwalls[t])}
            r["taichi_mpm88"] = q
            r["cost_ratio_vs_taichi"] = _paired(walls[t], pwalls[t])
            r["cost_ratio_of_medians"] = r["ns_per_particle_step"] / q["ns_per_particle_step"]
        out.append(r)
    return out


def run_bench(
    sizes: list[int],
    threads: list[int],
    steps: int,
    json_out: str | None,
    peer: bool = True,
    repeats: int = 5,
) -> int:
    """Run the benchmark grid, print a table, optionally write JSON; returns the exit code.

    With ``peer`` (and Taichi installed) the Taichi mpm88 fluid step runs at the same N and
    thread counts, its blocks interleaved with ours, and the cost ratio is reported."""
    max_threads = numba.config.NUMBA_NUM_THREADS
    usable = [t for t in threads if t <= max_threads]
    for t in threads:
        if t > max_threads:
            print(f"threads {t} skipped: only {max_threads} threads available", file=sys.stderr)
    if not usable:
        print("segmpm bench: no usable thread count", file=sys.stderr)
        return 2
    results = []
    print(f"segmpm {__version__} bench: seed chute (Fei model + sidewall + segregation), "
          f"{repeats} rounds of {steps}-step blocks interleaved over thread counts"
          f"{' and the Taichi peer' if peer else ''}; median block, median ratio within rounds; "
          f"numba {numba.__version__}, up to {max_threads} threads")  # fmt: skip
    print(f"{'points':>8} {'threads':>7} {'Mpart-steps/s':>14} {'ns/part-step':>13} "
          f"{'best ns':>8} {'speed-up':>8} {'first call s':>13} {'taichi ns':>10} "
          f"{'ours/taichi':>11}")  # fmt: skip
    for n in sizes:
        for r in bench_size(n, usable, steps, repeats, peer):
            results.append(r)
            sp = r.get(f"speedup_vs_{usable[0]}_threads")
            q = r.get("taichi_mpm88")
            extra = (f"{q['ns_per_particle_step']:>10.1f} {r['cost_ratio_vs_taichi']:>11.2f}"
                     if q is not None else f"{'-':>10} {'-':>11}")  # fmt: skip
            print(f"{r['n_points']:>8} {r['threads']:>7} {r['particle_steps_per_s'] / 1e6:>14.3f} "
                  f"{r['ns_per_particle_step']:>13.1f} {r['best_ns_per_particle_step']:>8.1f} "
                  f"{(f'{sp:.2f}' if sp else '-'):>8} {r['first_call_s']:>13.2f} {extra}",
                  flush=True)  # fmt: skip
    doc = {
        "segmpm_version": __version__,
        "method": "rounds of interleaved blocks (every thread count, then the peer at the same "
        "thread count); cost = median block; ratios = median of the within-round ratios",
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
