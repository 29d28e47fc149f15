"""Checkpoint/resume equality, signals, numerical failure, atomic writes, determinism."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from conftest import SUBPROCESS_ENV, make_sim

from segmpm.cli import main
from segmpm.mpm.params import ST_LEFT_GRID
from segmpm.simulation import SimulationError

SMALL = [
    "geometry.depth=0.006", "geometry.length=0.002", "time.end=0.5",
    "output.profile_times=[0.0,0.1,0.25,0.5]", "output.checkpoint_interval=0.1",
    "output.fields=false", "output.figures=false", "output.progress=false",
    "time.chunk_steps=50",
]  # fmt: skip


def _args(*extra):
    out = []
    for s in (*SMALL, *extra):
        out += ["--set", s]
    return out


def _profiles(path: Path) -> xr.Dataset:
    with xr.open_dataset(path / "profiles.nc", engine="h5netcdf") as ds:
        return ds.load()


def _segmpm(args, **kw):
    return subprocess.Popen([sys.executable, "-m", "segmpm.cli", *args], env=SUBPROCESS_ENV, **kw)


@pytest.fixture(scope="module")
def reference_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("ref")
    assert main(["run", "--out", str(out), *_args()]) == 0
    return out


def test_same_configuration_same_result(reference_run, tmp_path):
    assert main(["run", "--out", str(tmp_path), *_args()]) == 0
    a, b = _profiles(reference_run), _profiles(tmp_path)
    for k in a.data_vars:
        np.testing.assert_array_equal(a[k].values, b[k].values, err_msg=k)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT, signal.SIGKILL])
def test_interrupt_then_resume_gives_the_same_result(reference_run, tmp_path, sig):
    out = tmp_path / "run"
    proc = _segmpm(["run", "--out", str(out), *_args()], stderr=subprocess.PIPE)
    # wait until the run has passed its first checkpoint, then interrupt at an arbitrary step
    deadline = time.time() + 300
    while time.time() < deadline:
        info = out / "run.json"
        if (out / "checkpoint" / "state.npz").exists() and info.exists():
            t = json.loads(info.read_text())["time"]
            if t >= 0.1:
                break
        if proc.poll() is not None:
            pytest.skip("the run finished before it could be interrupted")
        time.sleep(0.05)
    time.sleep(np.random.default_rng().uniform(0.05, 0.5))  # an arbitrary step
    proc.send_signal(sig)
    rc = proc.wait(timeout=120)
    if rc == 0:
        pytest.skip("the run finished before the signal arrived")
    if sig == signal.SIGKILL:
        assert rc == -signal.SIGKILL
    else:
        assert rc == 130, proc.stderr.read().decode()
        assert json.loads((out / "run.json").read_text())["status"] == "interrupted"
    # every output on disk is readable (nothing half-written)
    _profiles(out)
    res = subprocess.run([sys.executable, "-m", "segmpm.cli", "run", "--resume", "--out", str(out)],
                         capture_output=True, timeout=600, env=SUBPROCESS_ENV)  # fmt: skip
    assert res.returncode == 0, res.stderr.decode()
    a, b = _profiles(reference_run), _profiles(out)
    np.testing.assert_array_equal(a["time"].values, b["time"].values)
    for k in a.data_vars:
        np.testing.assert_array_equal(a[k].values, b[k].values, err_msg=k)
    assert json.loads((out / "run.json").read_text())["status"] == "completed"


def test_time_step_collapse_exits_3_with_diagnostic(tmp_path, capsys):
    # the stable step (≈ 7 µs here) is below the configured floor: the run must stop, not crawl
    rc = main(["run", "--out", str(tmp_path), *_args("time.dt_min=1e-4", "time.dt_max=1e-3")])
    assert rc == 3
    info = json.loads((tmp_path / "run.json").read_text())
    assert info["status"] == "failed"
    assert info["failure"]["reason"] == "time step collapsed"
    assert info["failure"]["max_signal_speed"] > 0
    assert "failed" in capsys.readouterr().err
    assert (tmp_path / "checkpoint" / "state.npz").exists()


def test_forced_nan_stops_with_point_named(tmp_path):
    from conftest import make_sim

    from segmpm.simulation import SimulationError

    sim = make_sim(["geometry.depth=0.004", "geometry.length=0.002"], out_dir=tmp_path)
    sim.engine.points.v[0, 17] = np.nan
    sim.prime()  # the edited initial state's stress and diagnostics
    with pytest.raises(SimulationError) as err:
        sim.advance_to(0.01)
    d = err.value.diagnostic
    assert d["reason"] == "non-finite state" and "time" in d and "point" in d


def test_atomic_write_survives_a_crash(tmp_path):
    from segmpm.io.atomic import write_with

    target = tmp_path / "f.txt"
    target.write_text("good")

    def crash(tmp):
        tmp.write_text("half")
        raise RuntimeError("crash during write")

    with pytest.raises(RuntimeError):
        write_with(target, crash)
    assert target.read_text() == "good"
    assert [p.name for p in tmp_path.iterdir()] == ["f.txt"]


def test_resume_refuses_without_checkpoint(tmp_path, capsys):
    assert main(["run", "--resume", "--out", str(tmp_path)]) == 2
    assert "no checkpoint" in capsys.readouterr().err
    assert os.listdir(tmp_path) == []


def test_compiled_time_loop_is_cached():
    """Numba will not cache a function that uses dynamic globals (``numba.get_num_threads()``
    called inside the loop is one) and then compiles it again in every process, one to two
    minutes before each run starts. The time loop and its kernels must be cacheable."""
    code = (
        "import warnings; warnings.simplefilter('always')\n"
        "from segmpm.config import load_config\n"
        "from segmpm.simulation import Simulation\n"
        "cfg = load_config(preset='chute_seed', overrides=['output.progress=false', 'geometry.depth=0.002',\n"
        "                             'geometry.length=0.002'])\n"
        "Simulation(cfg).advance(1.0, 3)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], env=SUBPROCESS_ENV, capture_output=True,
                       text=True, timeout=600)  # fmt: skip
    assert r.returncode == 0, r.stderr
    assert "Cannot cache" not in r.stderr, r.stderr


@pytest.mark.parametrize("preset", ["chute_seed", "chute_nonlocal"])
def test_results_do_not_depend_on_thread_count(preset):
    """One thread and two give the same state bit for bit: the local law, and the nonlocal one
    whose fluidity step runs its loops in order on one thread and in parallel regions on two."""
    import numba
    from conftest import make_sim

    if numba.config.NUMBA_NUM_THREADS < 2:
        pytest.skip("needs at least 2 numba threads")
    states = []
    for threads in (1, 2):
        sim = make_sim(["geometry.depth=0.006", "geometry.length=0.004",
                        f"grid.threads={threads}"], preset=preset)  # fmt: skip
        assert sim.threads == threads
        sim.advance_to(0.05)
        states.append({k: v.copy() for k, v in sim.engine.arrays().items()})
    numba.set_num_threads(1)  # back to the suite default (conftest)
    for k in states[0]:
        np.testing.assert_array_equal(states[0][k], states[1][k], err_msg=k)


def test_a_failed_state_is_not_advanced_again():
    """After a failure (here a point thrown out of the grid) the compiled loop is not re-entered:
    P2G of a point outside the grid would write outside the grid arrays."""
    sim = make_sim(["geometry.depth=0.002", "geometry.length=0.002", "geometry.headroom=0.5",
                    "segregation.model='none'"])  # fmt: skip
    sim.engine.points.v[1, -1] = 50.0  # one point leaves through the top within a few steps
    sim.prime()
    status, idx, _ = sim.advance(1.0, 1000)
    assert status == ST_LEFT_GRID and idx == sim.engine.n - 1
    with pytest.raises(SimulationError, match="cannot be advanced"):
        sim.advance(1.0, 10)


def test_diagnostics_are_those_of_the_last_step_of_a_call():
    """The output diagnostics (diag rows 1-5) are written on the last step of each call of the
    compiled loop only: after a call they must be that step's, i.e. their maxima are exactly the
    signal speed and viscosity the step's reductions handed to the time-step control, and a run
    chunked into calls ends in the same state, diagnostics included, as one call."""
    overrides = ["geometry.depth=0.004", "geometry.length=0.003"]
    one, two = make_sim(overrides), make_sim(overrides)
    one.advance(1.0, 300)
    for _ in range(3):
        status, _, n = two.advance(1.0, 100)
        assert status == 0 and n == 100
        d = two.engine.points.diag
        assert d[4].max() == two.clock["smax"] and d[5].max() == two.clock["numax"]
        assert np.all(d[1] >= 0.0) and np.any(d[1] > 0.0)  # the shear rate of a flowing chute
    a, b = one.engine.arrays(), two.engine.arrays()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    # a call that ends on the time target (not the step budget) also ends with a full step
    t = two.time + 7.3 * two.clock["dt"]
    two.advance(t, 10_000)
    assert abs(two.time - t) < 1e-15
    assert two.engine.points.diag[4].max() == two.clock["smax"]


def test_thread_policy_and_layer_recorded(tmp_path):
    """grid.threads = "auto" runs a small state serially, an integer is used as given; run.json
    records the count, why, and the threading layer (omp with a passive wait unless
    NUMBA_THREADING_LAYER)."""
    import os

    from segmpm import threads as T

    assert T.resolve("auto", 596) == (1, f"auto: 596 points < {T.SERIAL_BELOW} (serial below)")
    n, why = T.resolve("auto", 10 * T.SERIAL_BELOW)
    assert 1 <= n <= T.available_cores() and why.startswith("auto:")
    assert T.resolve(1, 10**6)[0] == 1
    assert main(["run", "--out", str(tmp_path), *_args("time.end=0.01",
                 "output.profile_times=[0.0]", "output.checkpoint_interval=0")]) == 0  # fmt: skip
    info = json.loads((tmp_path / "run.json").read_text())
    assert info["threads"] == 1 and "serial below" in info["threads_policy"]
    want = os.environ.get("NUMBA_THREADING_LAYER", "omp")
    assert info["threading_layer"] == want
    if want == "omp":
        assert os.environ.get("OMP_WAIT_POLICY") == "passive"


def test_threads_of_one_process_may_run_simulations_at_once():
    """Two threads of one process advancing two simulations at once (a dask worker with
    threads_per_worker > 1): the compiled loop is serialised, not aborted, and each result equals
    the same run done alone."""
    import threading

    over = ["geometry.depth=0.004", "geometry.length=0.002", "grid.threads=2"]
    alone = make_sim(over)
    for k in range(1, 5):
        alone.advance_to(0.005 * k)
    sims = [make_sim(over), make_sim(over)]
    errors = []

    def go(s):
        try:
            for k in range(1, 5):
                s.advance_to(0.005 * k)
        except Exception as exc:  # noqa: BLE001
            errors.append(exc)

    ts = [threading.Thread(target=go, args=(s,)) for s in sims]
    for t in ts:
        t.start()
    for t in ts:
        t.join()
    assert not errors
    for s in sims:
        np.testing.assert_array_equal(s.engine.points.x, alone.engine.points.x)
