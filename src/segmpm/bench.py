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
from .io.atomic import write_json

#: the variants ``segmpm bench --variants`` can time: the preset each one starts from and the
#: overrides on it (the local default and the grain-calibrated nonlocal model). The former
#: plane-strain engine's ``generic-*`` A/B variants went with that engine (2-D A/B against the
#: commit before the generic engine: benchmarks/ab2d_identity.py).
VARIANTS = {
    "local": ("chute_seed", ()),
    "nonlocal": ("chute_nonlocal", ()),
}


def _config_for(n_points: int, variant: str = "local"):
    from .config import apply_overrides, preset_data, resolve_extends, validate_data

    preset, extra = VARIANTS[variant]
    data = resolve_extends(preset_data(preset), None)
    quiet = ["output.progress=false", "output.fields=false", *extra]
    base = validate_data(apply_overrides(data, quiet))
    h = base.grid.cell_size
    px, py = base.grid.points_per_axis(2)
    rows = round(base.geometry.depth / (h / py))
    cells = max(2, round(n_points / rows / px))
    # the production configuration: the concentration subcycle every segregation.dt = 1e-3 s,
    # i.e. about every 70 steps, so a few hundred timed steps include several of them
    return validate_data(apply_overrides(data, [*quiet, f"geometry.length={cells * h!r}"]))


class Peer:
    """The Taichi mpm88 peer at one N and thread count, in its own process
    (``python -m segmpm.bench_taichi --serve``), timing one block per :meth:`block` call."""

    def __init__(self, n_points: int, threads: int, steps: int, order: str = "random"):
        cmd = [sys.executable, "-m", "segmpm.bench_taichi", "--serve", "--n", str(n_points),
               "--threads", str(threads), "--steps", str(steps), "--order", order]  # fmt: skip
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


#: the peer's initial particle orders: Taichi mpm88's random order, and segmpm's sorted lattice
PEER_ORDERS = ("random", "sorted")


def _peers(n: int, threads: list[int], steps: int) -> dict[tuple[int, str], Peer]:
    """One peer per thread count and initial order; empty if Taichi is not installed or a peer
    fails to start."""
    if importlib.util.find_spec("taichi") is None:
        return {}
    peers: dict[tuple[int, str], Peer] = {}
    try:
        for t in threads:
            for o in PEER_ORDERS:
                peers[t, o] = Peer(n, t, steps, o)
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
    n_points: int,
    threads: list[int],
    steps: int,
    repeats: int = 5,
    peer: bool = True,
    variants: tuple[str, ...] = ("local",),
) -> list[dict[str, Any]]:
    """Time the seed chute with about ``n_points`` points at every thread count in ``threads``
    for each variant (``VARIANTS``: the local default and the grain-calibrated nonlocal model),
    and the Taichi peer if ``peer``, their blocks interleaved round by round; one result per
    variant and thread count. Variants after the first get their cost ratio to the first."""
    from .simulation import Simulation

    sims = {v: Simulation(_config_for(n_points, v)) for v in variants}
    n = sims[variants[0]].engine.n
    first: dict[tuple[str, int], float] = {}
    for v, sim in sims.items():
        for t in threads:
            sim.threads = t  # the simulation sets numba's thread count on every call
            t0 = time.perf_counter()
            sim.advance(1.0, 1)  # compiles (or loads the cache) on the first thread count
            first[v, t] = time.perf_counter() - t0
        sim.advance(1.0, max(10, steps // 10))  # leave the start-up state
    peers = _peers(n, threads, steps) if peer else {}
    walls: dict[tuple[str, int], list[float]] = {(v, t): [] for v in variants for t in threads}
    pwalls: dict[tuple[int, str], list[float]] = {k: [] for k in peers}
    try:
        for _ in range(max(1, repeats)):
            for t in threads:
                for v, sim in sims.items():
                    sim.threads = t
                    w0, s0 = sim.wall_time, sim.steps
                    sim.advance(1.0, steps)
                    if sim.steps - s0 != steps:
                        raise RuntimeError(
                            f"bench: the chute stopped after {sim.steps - s0} of {steps} steps"
                        )
                    walls[v, t].append(sim.wall_time - w0)
                for o in PEER_ORDERS:
                    if (t, o) in peers:
                        pwalls[t, o].append(peers[t, o].block())
    finally:
        for q in peers.values():
            q.close()
    out = []
    for v in variants:
        for t in threads:
            w = walls[v, t]
            r: dict[str, Any] = {"variant": v, "n_points": n, "threads": t,
                                 **summarize(n, steps, w), "first_call_s": first[v, t]}  # fmt: skip
            if t != threads[0]:
                r[f"speedup_vs_{threads[0]}_threads"] = _paired(walls[v, threads[0]], w)
            if v != variants[0]:
                r[f"cost_ratio_vs_{variants[0]}"] = _paired(w, walls[variants[0], t])
            for o in PEER_ORDERS:  # "taichi_mpm88" is the random order, "..._sorted" segmpm's
                if (t, o) not in peers:
                    continue
                tag = "" if o == "random" else f"_{o}"
                q = {**peers[t, o].facts, **summarize(n, steps, pwalls[t, o])}
                r[f"taichi_mpm88{tag}"] = q
                r[f"cost_ratio_vs_taichi{tag}"] = _paired(w, pwalls[t, o])
                r[f"cost_ratio_of_medians{tag}"] = (
                    r["ns_per_particle_step"] / q["ns_per_particle_step"]
                )
            out.append(r)
    return out


def run_bench(
    sizes: list[int],
    threads: list[int],
    steps: int,
    json_out: str | None,
    peer: bool = True,
    repeats: int = 5,
    variants: tuple[str, ...] = ("local",),
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
    print(f"{'variant':>9} {'points':>8} {'threads':>7} {'Mpart-steps/s':>14} {'ns/part-step':>13} "
          f"{'best ns':>8} {'speed-up':>8} {'first call s':>13} {'taichi ns':>10} "
          f"{'ours/taichi':>11} {'sorted ns':>10} {'ours/sorted':>11} "
          f"{'vs ' + variants[0]:>10}")  # fmt: skip
    for n in sizes:
        for r in bench_size(n, usable, steps, repeats, peer, tuple(variants)):
            results.append(r)
            sp = r.get(f"speedup_vs_{usable[0]}_threads")
            q = r.get("taichi_mpm88")
            extra = (f"{q['ns_per_particle_step']:>10.1f} {r['cost_ratio_vs_taichi']:>11.2f}"
                     if q is not None else f"{'-':>10} {'-':>11}")  # fmt: skip
            qs = r.get("taichi_mpm88_sorted")
            extra += (f" {qs['ns_per_particle_step']:>10.1f} "
                      f"{r['cost_ratio_vs_taichi_sorted']:>11.2f}"
                      if qs is not None else f" {'-':>10} {'-':>11}")  # fmt: skip
            vr = r.get(f"cost_ratio_vs_{variants[0]}")
            print(f"{r['variant']:>9} {r['n_points']:>8} {r['threads']:>7} "
                  f"{r['particle_steps_per_s'] / 1e6:>14.3f} "
                  f"{r['ns_per_particle_step']:>13.1f} {r['best_ns_per_particle_step']:>8.1f} "
                  f"{(f'{sp:.2f}' if sp else '-'):>8} {r['first_call_s']:>13.2f} {extra} "
                  f"{(f'{vr:.2f}' if vr else '-'):>10}", flush=True)  # fmt: skip
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


# ---------------------------------------------------------------------------------- contention
def _busy_process(core: int | None) -> subprocess.Popen:
    """A competing busy loop (another user's job), pinned to ``core`` when given."""
    code = "while True:\n    pass\n"
    p = subprocess.Popen([sys.executable, "-c", code])
    if core is not None:
        try:
            import os

            os.sched_setaffinity(p.pid, {core})
        except (AttributeError, OSError):
            pass
    return p


def bench_contended(sizes: list[int], threads: list[int], steps: int, repeats: int = 5,
                    seed_end: float = 1.0) -> dict[str, Any]:  # fmt: skip
    """The step with and without one competing busy process (pinned to the last core), for each
    thread count and size, in one run: rounds alternate an idle block and a contended block, and
    the slowdown is the median of the within-round ratios. Then the default seed case (``segmpm
    run`` to ``seed_end``) alone, beside the busy process, and two such runs started together."""
    import os

    try:
        cores = sorted(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = list(range(os.cpu_count() or 1))
    busy_core = cores[-1] if len(cores) > 1 else None
    from .simulation import Simulation

    rows = []
    for n_req in sizes:
        sim = Simulation(_config_for(n_req))
        n = sim.engine.n
        st = max(steps, int(4e6 / max(n, 1)))  # blocks of ≥ 4e6 particle-steps
        for t in threads:
            sim.threads = t
            sim.advance(1.0, 10)
        sim.advance(1.0, max(10, st // 10))
        idle: dict[int, list[float]] = {t: [] for t in threads}
        cont: dict[int, list[float]] = {t: [] for t in threads}
        for _ in range(max(1, repeats)):
            for t in threads:
                sim.threads = t
                w0 = sim.wall_time
                sim.advance(1.0, st)
                idle[t].append(sim.wall_time - w0)
            busy = _busy_process(busy_core)
            time.sleep(0.3)
            try:
                for t in threads:
                    sim.threads = t
                    w0 = sim.wall_time
                    sim.advance(1.0, st)
                    cont[t].append(sim.wall_time - w0)
            finally:
                busy.kill()
                busy.wait()
        for t in threads:
            rows.append({"n_points": n, "threads": t, "steps_per_block": st,
                         "idle": summarize(n, st, idle[t]), "contended": summarize(n, st, cont[t]),
                         "slowdown": _paired(cont[t], idle[t])})  # fmt: skip

    # the default run as a user starts it: alone, beside a busy process, and two at once
    def seed_run(tag: str) -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-m", "segmpm.cli", "run", "--out",
                                 f"/tmp/segmpm-bench-{os.getpid()}-{tag}", "--set",
                                 f"time.end={seed_end}", "--set", "output.fields=false",
                                 "--set", "output.figures=false", "--set", "output.progress=false"],
                                stderr=subprocess.DEVNULL)  # fmt: skip

    def timed(procs: list[subprocess.Popen]) -> float:
        t0 = time.perf_counter()
        for p in procs:
            p.wait()
        return time.perf_counter() - t0

    seed_run("warm").wait()  # compile cache warm, first-run effects out of the timing
    runs = {"alone": [], "beside_busy": [], "two_together": []}
    for r in range(max(1, min(repeats, 3))):
        runs["alone"].append(timed([seed_run(f"a{r}")]))
        busy = _busy_process(busy_core)
        time.sleep(0.3)
        try:
            runs["beside_busy"].append(timed([seed_run(f"b{r}")]))
        finally:
            busy.kill()
            busy.wait()
        runs["two_together"].append(timed([seed_run(f"c{r}"), seed_run(f"d{r}")]))
    seed = {k: statistics.median(v) for k, v in runs.items()}
    seed.update({"all": runs, "slowdown_beside_busy": seed["beside_busy"] / seed["alone"],
                 "slowdown_two_together": seed["two_together"] / seed["alone"],
                 "time_end_s": seed_end})  # fmt: skip
    return {"step": rows, "seed_run_wall_s": seed, "busy_core": busy_core, "cores": cores}


def run_contended(sizes: list[int], threads: list[int], steps: int, json_out: str | None,
                  repeats: int = 5) -> int:  # fmt: skip
    """``segmpm bench --contended``: print and optionally write :func:`bench_contended`."""
    from .threads import threading_layer

    res = bench_contended(sizes, threads, steps, repeats)
    print(f"segmpm {__version__} bench --contended: one busy process pinned to core "
          f"{res['busy_core']}; threading layer {threading_layer()}")  # fmt: skip
    print(f"{'points':>8} {'threads':>7} {'idle ns/pst':>12} {'busy ns/pst':>12} {'slowdown':>9}")
    for r in res["step"]:
        print(f"{r['n_points']:>8} {r['threads']:>7} {r['idle']['ns_per_particle_step']:>12.1f} "
              f"{r['contended']['ns_per_particle_step']:>12.1f} {r['slowdown']:>9.2f}")  # fmt: skip
    s = res["seed_run_wall_s"]
    print(f"default seed run to t = {s['time_end_s']:g} s (wall, median): alone {s['alone']:.2f} s, "
          f"beside a busy process {s['beside_busy']:.2f} s ({s['slowdown_beside_busy']:.2f}x), "
          f"two together {s['two_together']:.2f} s ({s['slowdown_two_together']:.2f}x)")  # fmt: skip
    doc = {
        "segmpm_version": __version__,
        "threading_layer": threading_layer(),
        "machine": {
            "python": platform.python_version(),
            "processor": platform.processor(),
            "numba": numba.__version__,
            "cores": res["cores"],
        },  # fmt: skip
        **res,
    }
    if json_out:
        write_json(json_out, doc)
    return 0
