"""Thread policy and threading layer of the compiled loop (docs/performance.md, "Threads").

* **Threading layer.** Numba's parallel regions end in a barrier. With the OpenMP layer's default
  (active) wait policy the waiting threads spin, so a core taken by another process makes every
  barrier wait for a time slice: a 2-thread run beside one busy process was 3–300× slower. The
  ``workqueue`` layer does not spin, but its launch (a condition-variable hand-off to a worker,
  even on one thread) cost ≈ 0.1 ms per parallel region: the default seed case (596 points, a few
  regions per step) ran 12× slower than with OpenMP (8.6 s against 0.7 s for 0.2 s of flow,
  docs/performance.md "Threads"). segmpm therefore pins the ``omp`` layer with
  ``OMP_WAIT_POLICY=passive`` (waiting threads sleep; one thread runs a region inline), both set
  before any parallel kernel runs (``configure_layer``, called when the package is imported);
  ``NUMBA_THREADING_LAYER`` and ``OMP_WAIT_POLICY`` in the environment still win. The layer in
  use is recorded in ``run.json``.
* **Concurrent launches.** Numba's workqueue layer aborts the process when two threads of one
  process launch parallel kernels at once; whichever layer is in use, every call of the compiled loop from
  :class:`segmpm.simulation.Simulation` holds ``KERNEL_LOCK``: several threads of one process (a
  dask worker with ``threads_per_worker > 1``) are safe, and take turns.
* **Thread count** (``grid.threads = "auto"``, the default): one thread below
  ``SERIAL_BELOW`` material points (a parallel region then costs more than it saves; measured in
  docs/performance.md); else the cores this process may use (its CPU affinity and the cgroup CPU
  quota), less the cores other processes keep busy (sampled from /proc for 0.25 s when the
  simulation is built), at least one. An integer ``grid.threads`` is used as given (capped at Numba's pool). Inside a sweep
  every member uses one thread (one process per core).
"""

from __future__ import annotations

import math
import os
import threading
from pathlib import Path

#: serialises the compiled loop between the threads of one process (see the module docstring)
KERNEL_LOCK = threading.RLock()

#: below this many material points the loop runs on one thread (docs/performance.md, "Threads")
SERIAL_BELOW = 20_000

#: the threading layer segmpm asks Numba for
LAYER = "omp"


def configure_layer() -> str:
    """Ask Numba for ``LAYER`` unless ``NUMBA_THREADING_LAYER`` is set; returns the request."""
    import numba

    env = os.environ.get("NUMBA_THREADING_LAYER")
    if env:
        return env
    # read by libgomp when it is loaded, i.e. at Numba's first parallel launch
    os.environ.setdefault("OMP_WAIT_POLICY", "passive")
    numba.config.THREADING_LAYER = LAYER
    return LAYER


def threading_layer() -> str:
    """The layer Numba actually uses ("not started yet" before the first parallel kernel)."""
    import numba

    try:
        return str(numba.threading_layer())
    except ValueError:
        return "not started yet"


def _cgroup_cpus() -> float | None:
    """CPUs of the cgroup CPU quota (v2 ``cpu.max``, v1 ``cfs_quota_us``), None if unlimited."""
    try:
        txt = Path("/sys/fs/cgroup/cpu.max").read_text().split()
        if txt and txt[0] != "max":
            return float(txt[0]) / float(txt[1])
    except (OSError, ValueError, IndexError):
        pass
    try:
        q = float(Path("/sys/fs/cgroup/cpu/cpu.cfs_quota_us").read_text())
        p = float(Path("/sys/fs/cgroup/cpu/cpu.cfs_period_us").read_text())
        if q > 0 and p > 0:
            return q / p
    except (OSError, ValueError):
        pass
    return None


def available_cores() -> int:
    """Cores this process may run on: its affinity, capped by the cgroup quota (at least 1)."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        n = os.cpu_count() or 1
    quota = _cgroup_cpus()
    if quota is not None:
        n = min(n, max(1, math.floor(quota + 1e-9)))
    return max(1, n)


def _cpu_jiffies() -> tuple[float, float] | None:
    """(busy jiffies of the whole machine, jiffies of this process) from /proc."""
    try:
        f = Path("/proc/stat").read_text().splitlines()[0].split()[1:]
        v = [float(x) for x in f]
        idle = v[3] + (v[4] if len(v) > 4 else 0.0)  # idle + iowait
        busy = sum(v[:8]) - idle  # user nice system idle iowait irq softirq steal
        st = Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()
        own = float(st[11]) + float(st[12])  # utime + stime of this process (all its threads)
        return busy, own
    except (OSError, ValueError, IndexError):
        return None


def busy_cores(sample: float = 0.25) -> int:
    """Cores other processes keep busy now: the machine's busy time less this process's over a
    short sample (from /proc; else the 1-minute load average), rounded."""
    a = _cpu_jiffies()
    if a is not None:
        import time

        t0 = time.monotonic()
        time.sleep(sample)
        b = _cpu_jiffies()
        dt = time.monotonic() - t0
        if b is not None and dt > 0:
            hz = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
            others = ((b[0] - a[0]) - (b[1] - a[1])) / hz / dt
            return max(0, round(others))
    try:
        return max(0, round(os.getloadavg()[0]))
    except (AttributeError, OSError):
        return 0


def resolve(setting: int | str, n_points: int) -> tuple[int, str]:
    """(thread count, reason) for ``grid.threads`` = ``setting`` and a state of ``n_points``."""
    import numba

    pool = numba.config.NUMBA_NUM_THREADS
    if setting != "auto":
        n = int(setting)
        if n <= 0:  # 0: Numba's default pool (the former meaning of 0)
            return pool, "grid.threads = 0: numba's default"
        return min(n, pool), f"grid.threads = {n}" + (f" (capped at {pool})" if n > pool else "")
    if n_points < SERIAL_BELOW:
        return 1, f"auto: {n_points} points < {SERIAL_BELOW} (serial below)"
    cores = available_cores()
    free = max(1, cores - busy_cores())
    n = max(1, min(pool, free))
    return n, f"auto: {cores} cores available, {cores - free} busy with other work"
