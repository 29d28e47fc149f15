"""The run's surroundings: bad output paths, write failures mid-run (exit 4), the lock on OUT,
no silent overwrite, requeue-safe --resume, a responsive first run, file modes, atomic figures.

Every fault is made so that it also happens as root (who ignores chmod): a file as --out,
RLIMIT_FSIZE (EFBIG) in a subprocess, an ENOSPC injected into the atomic writer.
"""

from __future__ import annotations

import errno
import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from conftest import SUBPROCESS_ENV, make_sim

from segmpm import simulation as simmod
from segmpm.cli import main
from segmpm.io import atomic
from segmpm.io import outdir as od
from segmpm.io.checkpoint import load_checkpoint

# a small, fast run: 128 points, ≈ 4500 steps, checkpoints every 0.02 s
TINY = [
    "geometry.depth=0.004", "geometry.length=0.002", "time.end=0.1",
    "output.profile_times=[0.0,0.02,0.05,0.1]", "output.checkpoint_interval=0.02",
    "output.fields=false", "output.figures=false", "output.progress=false",
    "time.chunk_steps=50",
]  # fmt: skip


def _args(*extra: str, base=TINY) -> list[str]:
    out: list[str] = []
    for s in (*base, *extra):
        out += ["--set", s]
    return out


def _profiles(path: Path) -> xr.Dataset:
    with xr.open_dataset(path / "profiles.nc", engine="h5netcdf") as ds:
        return ds.load()


def _same_profiles(a: Path, b: Path) -> None:
    x, y = _profiles(a), _profiles(b)
    np.testing.assert_array_equal(x["time"].values, y["time"].values)
    for k in x.data_vars:
        np.testing.assert_array_equal(x[k].values, y[k].values, err_msg=k)


def _temporaries(out: Path) -> list[Path]:
    return [p for p in out.rglob("*") if ".tmp" in p.name or p.name.startswith(".vtk.")]


def _info(out: Path) -> dict:
    return json.loads((out / "run.json").read_text())


def _cli(*args: str, **kw) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "segmpm.cli", *args], env=SUBPROCESS_ENV,
                            **kw)  # fmt: skip


@pytest.fixture(scope="module")
def tiny_reference(tmp_path_factory):
    out = tmp_path_factory.mktemp("tiny-ref")
    assert main(["run", "--out", str(out), *_args()]) == 0
    return out


# ------------------------------------------------------------------------- 1. paths and disks


def test_out_is_a_file_exits_2_before_the_run(tmp_path, capsys):
    f = tmp_path / "results"
    f.write_text("not a directory")
    assert main(["run", "--out", str(f), *_args()]) == 2
    err = capsys.readouterr().err
    assert str(f) in err and "not a directory" in err and "Traceback" not in err
    assert err.count("\n") == 1  # one paragraph
    assert f.read_text() == "not a directory"


def test_out_under_a_file_exits_2(tmp_path, capsys):
    f = tmp_path / "results"
    f.write_text("x")
    assert main(["run", "--out", str(f / "a" / "b"), *_args()]) == 2
    err = capsys.readouterr().err
    assert str(f) in err and "is a file" in err and "Traceback" not in err
    # --resume too (without a configuration it looks for OUT/config.toml)
    assert main(["run", "--resume", "--out", str(f)]) == 2
    assert "not a directory" in capsys.readouterr().err


def test_a_sub_folder_that_is_a_file_exits_2(tmp_path, capsys):
    (tmp_path / "checkpoint").write_text("mine")
    assert main(["run", "--out", str(tmp_path), "--overwrite", *_args()]) == 2
    err = capsys.readouterr().err
    assert "checkpoint" in err and "is a file" in err
    assert not (tmp_path / "run.json").exists()


@pytest.mark.skipif(os.geteuid() == 0, reason="root ignores the permission bits")
def test_unwritable_out_exits_2(tmp_path, capsys):
    d = tmp_path / "ro"
    d.mkdir()
    d.chmod(0o500)
    try:
        assert main(["run", "--out", str(d), *_args()]) == 2
        err = capsys.readouterr().err
        assert str(d) in err and "Permission denied" in err
        assert main(["run", "--out", str(d / "sub"), *_args()]) == 2
        assert "cannot be created" in capsys.readouterr().err
    finally:
        d.chmod(0o700)


class _Fail:
    """Replaces ``atomic._commit``: raises ``OSError(code)`` at the ``nth`` write of a file named
    ``name`` (and at every later one if ``sticky``)."""

    def __init__(self, name: str, nth: int, code: int = errno.ENOSPC, sticky: bool = False):
        self.name, self.nth, self.code, self.sticky = name, nth, code, sticky
        self.count = 0
        self.real = atomic._commit

    def __call__(self, tmp: Path, path: Path) -> None:
        if path.name == self.name:
            self.count += 1
            if self.count == self.nth or (self.sticky and self.count > self.nth):
                tmp.write_bytes(b"partial")  # the temporary file exists and holds junk
                raise OSError(self.code, os.strerror(self.code))
        self.real(tmp, path)


def test_enospc_during_a_checkpoint_keeps_the_previous_one(tmp_path, capsys, monkeypatch,
                                                           tiny_reference):  # fmt: skip
    fail = _Fail("state.npz", nth=3)  # the checkpoints at t = 0, 0.02, then 0.04 fails
    monkeypatch.setattr(atomic, "_commit", fail)
    assert main(["run", "--out", str(tmp_path), "--resume", *_args()]) == 4
    err = capsys.readouterr().err
    ckpt = tmp_path / "checkpoint" / "state.npz"
    assert str(ckpt) in err and "No space left on device" in err and "ENOSPC" in err
    assert "Traceback" not in err
    info = _info(tmp_path)
    assert info["status"] == "failed"
    f = info["failure"]
    assert f["reason"] == "output could not be written" and f["path"] == str(ckpt)
    assert f["errno"] == "ENOSPC" and f["last_checkpoint_time"] == pytest.approx(0.02)
    assert _temporaries(tmp_path) == []
    _, meta = load_checkpoint(ckpt)  # the previous checkpoint is complete and loads
    assert meta["time"] == pytest.approx(0.02)
    assert list(_profiles(tmp_path)["time"].values) == [0.0, 0.02]
    # once the disk has room, the same command line continues, bit for bit
    monkeypatch.setattr(atomic, "_commit", fail.real)
    assert main(["run", "--out", str(tmp_path), "--resume", *_args()]) == 0
    _same_profiles(tiny_reference, tmp_path)


def test_enospc_on_the_profiles_keeps_the_written_ones(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(atomic, "_commit", _Fail("profiles.nc", nth=3))
    assert main(["run", "--out", str(tmp_path), *_args()]) == 4
    err = capsys.readouterr().err
    assert str(tmp_path / "profiles.nc") in err and "No space left" in err
    assert list(_profiles(tmp_path)["time"].values) == [0.0, 0.02]
    assert _info(tmp_path)["failure"]["path"] == str(tmp_path / "profiles.nc")
    assert _temporaries(tmp_path) == []


def test_eio_on_run_json_still_exits_4(tmp_path, capsys, monkeypatch):
    # run.json cannot be written after its first version: the run stops (exit 4) and says so
    monkeypatch.setattr(atomic, "_commit", _Fail("run.json", nth=2, code=errno.EIO, sticky=True))
    assert main(["run", "--out", str(tmp_path), *_args()]) == 4
    err = capsys.readouterr().err
    assert "run.json" in err and "could not be updated" in err and "EIO" in err
    assert _info(tmp_path)["status"] == "running"  # the last version that could be written
    assert _temporaries(tmp_path) == []
    load_checkpoint(tmp_path / "checkpoint" / "state.npz")


def _loaded_kernels(over: list[str]):
    """Generate the kernel sources of the run ``segmpm run`` makes of ``over`` (the built-in
    preset) and compile its time loop, or load it from Numba's cache, in this process: the
    subprocess below then only reads them. (Under RLIMIT_FSIZE the generated sources and Numba's
    cache files would be the first writes to hit the limit, before the run's outputs.)"""
    from segmpm.config import DEFAULT_PRESET

    sim = make_sim(over, preset=DEFAULT_PRESET)
    sim.advance(sim.time, 0)  # the zero-step call of the run: compiles or loads, changes nothing


def _limited(limit: int):
    def pre():
        import resource

        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # writes past the limit fail with EFBIG
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    return pre


def test_file_size_limit_mid_run_exits_4_and_resumes(tmp_path):
    """RLIMIT_FSIZE between the size of profiles.nc with one and with two output times: the
    second profile write fails with EFBIG (a real OS error, also for root)."""
    over = [*TINY, "output.profile_bin=2e-5"]
    sim = make_sim(over, out_dir=tmp_path / "probe")
    sizes = []
    from segmpm.io.profiles import ProfileWriter

    w = ProfileWriter(tmp_path / "probe.nc", sim.edges, sim._attrs())
    for t in (0.0, 0.02):
        w.add(t, sim.profiles(), sim.segregation_diagnostics())
        sizes.append(w.path.stat().st_size)
    sim.save_checkpoint(tmp_path / "probe.npz")
    limit = (sizes[0] + sizes[1]) // 2
    assert (tmp_path / "probe.npz").stat().st_size < limit, "checkpoint must fit"
    _loaded_kernels(over)
    out = tmp_path / "run"
    proc = _cli("run", "--out", str(out), *_args(base=over), stderr=subprocess.PIPE,
                preexec_fn=_limited(limit))  # fmt: skip
    _, err = proc.communicate(timeout=600)
    err = err.decode()
    assert proc.returncode == 4, err
    assert str(out / "profiles.nc") in err and "File too large" in err and "EFBIG" in err
    assert "Traceback" not in err
    info = _info(out)
    assert info["status"] == "failed" and info["failure"]["errno"] == "EFBIG"
    assert _temporaries(out) == []
    assert list(_profiles(out)["time"].values) == [0.0]
    # the checkpoint at t = 0.02 was not reached: the one at 0 is kept; --resume continues
    assert load_checkpoint(out / "checkpoint" / "state.npz")[1]["time"] == 0.0
    r = subprocess.run([sys.executable, "-m", "segmpm.cli", "run", "--resume", "--out", str(out)],
                       env=SUBPROCESS_ENV, capture_output=True, timeout=600)  # fmt: skip
    assert r.returncode == 0, r.stderr.decode()
    assert list(_profiles(out)["time"].values) == [0.0, 0.02, 0.05, 0.1]


def test_file_size_limit_on_the_first_checkpoint(tmp_path):
    _loaded_kernels(TINY)
    out = tmp_path / "run"
    proc = _cli("run", "--out", str(out), *_args(), stderr=subprocess.PIPE,
                preexec_fn=_limited(8000))  # fmt: skip
    _, err = proc.communicate(timeout=600)
    err = err.decode()
    assert proc.returncode == 4, err
    assert str(out / "checkpoint" / "state.npz") in err and "EFBIG" in err
    assert "no checkpoint was written yet" in err
    assert _info(out)["status"] == "failed"
    assert _temporaries(out) == []
    assert not (out / "checkpoint" / "state.npz").exists()


def test_kernel_cache_that_cannot_be_written_exits_4_before_the_run(tmp_path):
    """A cold kernel cache on a full file system (RLIMIT_FSIZE below the size of the generated
    kernel source): the run stops with exit 4 naming the cache and SEGMPM_CACHE_DIR, before it
    writes anything, and leaves no partial source behind (neither in the cache nor a private
    temporary copy)."""
    out, cache, tmp = tmp_path / "run", tmp_path / "cache", tmp_path / "tmp"
    tmp.mkdir()
    env = {**SUBPROCESS_ENV, "SEGMPM_CACHE_DIR": str(cache), "TMPDIR": str(tmp)}
    proc = subprocess.Popen([sys.executable, "-m", "segmpm.cli", "run", "--out", str(out),
                             *_args()], env=env, stderr=subprocess.PIPE,
                            preexec_fn=_limited(8000))  # fmt: skip
    _, err = proc.communicate(timeout=600)
    err = err.decode()
    assert proc.returncode == 4, err
    assert "Traceback" not in err
    assert "kernel cache" in err and "SEGMPM_CACHE_DIR" in err and "File too large" in err
    assert not (out / "run.json").exists() and not (out / "checkpoint").exists()
    assert list(tmp.iterdir()) == []
    assert not list(cache.rglob("kernels_d*"))  # the source (> 8000 bytes) was never complete


class _NoProfiles:
    """A profile writer that writes nothing: only the run's particle snapshot is under test."""

    def add(self, *args) -> None:
        pass


def test_vtk_write_failure_leaves_no_temporary_vtu(tmp_path, monkeypatch):
    from segmpm.io import vtk as vtkmod

    sim = make_sim([*TINY, "output.fields=true"])
    series = vtkmod.VTKSeries(tmp_path / "fields")
    sim._output(0.0, _NoProfiles(), series)  # the run's snapshot of the points
    assert len(series.entries) == 1
    real = vtkmod.pointsToVTK

    def full_disk(path, *a, **kw):
        written = real(path, *a, **kw)  # the file exists, then the disk is full
        raise OSError(errno.ENOSPC, "No space left on device")
        return written

    monkeypatch.setattr(vtkmod, "pointsToVTK", full_disk)
    with pytest.raises(atomic.OutputWriteError) as exc:
        sim._output(0.01, _NoProfiles(), series)
    assert exc.value.path == tmp_path / "fields" / "particles_0001.vtu"
    assert exc.value.errno == errno.ENOSPC
    assert sorted(p.name for p in (tmp_path / "fields").iterdir()) == [
        "particles.pvd",
        "particles_0000.vtu",
    ]
    assert len(series.entries) == 1
    # and at the rename of the snapshot (the injected writer failure)
    monkeypatch.setattr(vtkmod, "pointsToVTK", real)
    monkeypatch.setattr(atomic, "_commit", _Fail("particles_0001.vtu", nth=1))
    with pytest.raises(atomic.OutputWriteError):
        sim._output(0.01, _NoProfiles(), series)
    assert _temporaries(tmp_path) == []


# ------------------------------------------------------------------------- 6. modes, figures


@pytest.mark.parametrize("mask", [0o022, 0o002, 0o027])
def test_outputs_honour_the_umask(tmp_path, mask):
    old = os.umask(mask)
    try:
        assert main(["run", "--out", str(tmp_path), *_args("time.end=0.02", "output.fields=true",
                     "output.figures=true", "output.profile_times=[0.0,0.02]")]) == 0  # fmt: skip
    finally:
        os.umask(old)
    files = [p for p in tmp_path.rglob("*") if p.is_file()]
    names = {str(p.relative_to(tmp_path)) for p in files}
    assert {"profiles.nc", "run.json", "config.toml", "checkpoint/state.npz",
            "fields/particles.pvd", "fields/particles_0001.vtu",
            "figures/profiles.png"} <= names  # fmt: skip
    for p in files:
        assert p.stat().st_mode & 0o777 == 0o666 & ~mask, (p, oct(p.stat().st_mode))
    assert (tmp_path / "figures" / "profiles.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_figures_are_written_atomically(tmp_path, monkeypatch, tiny_reference):
    from segmpm.io.figures import plot_profiles

    png = tmp_path / "figures" / "profiles.png"
    ds = _profiles(tiny_reference)
    plot_profiles(ds, png)
    good = png.read_bytes()
    assert good[:4] == b"\x89PNG" and len(good) > 10_000
    monkeypatch.setattr(atomic, "_commit", _Fail("profiles.png", nth=1))
    with pytest.raises(atomic.OutputWriteError) as exc:
        plot_profiles(ds, png)
    assert exc.value.path == png
    assert png.read_bytes() == good
    assert _temporaries(tmp_path) == []
    # `segmpm plot` reports it as a write failure (exit 4), not a traceback
    (tmp_path / "profiles.nc").write_bytes((tiny_reference / "profiles.nc").read_bytes())
    monkeypatch.setattr(atomic, "_commit", _Fail("profiles.png", nth=1))
    assert main(["plot", str(tmp_path)]) == 4


def test_time_step_collapse_reports_the_collapsed_step(tmp_path, capsys):
    rc = main(["run", "--out", str(tmp_path), *_args("time.dt_min=1e-4", "time.dt_max=1e-3")])
    assert rc == 3
    f = _info(tmp_path)["failure"]
    assert f["reason"] == "time step collapsed"
    assert 0 < f["dt_collapsed"] < f["dt_min"] == 1e-4
    assert "Courant" in f["dt_limit"]
    from segmpm.config import DEFAULT_PRESET

    prm = make_sim(TINY, preset=DEFAULT_PRESET).engine.prm[0]  # `segmpm run` without CONFIG
    h, cfl = prm["h"], prm["cfl"]
    assert f["dt_collapsed"] == pytest.approx(cfl * h / max(f["max_signal_speed"],
                                                            prm["c_floor"]))  # fmt: skip
    want = f"dt = {f['dt_collapsed']:.3g} s < time.dt_min = 0.0001 s"
    assert want in f["message"] and want in capsys.readouterr().err


# ------------------------------------------------------------------------- 2. the lock


HOLDER = """
import sys, time
from segmpm.io.outdir import OutLock
lock = OutLock(sys.argv[1]).acquire()
print(lock.mode, flush=True)
time.sleep(120)
"""


def test_a_locked_out_exits_2_naming_the_holder_and_is_freed_by_sigkill(tmp_path, capsys):
    out = tmp_path / "run"
    out.mkdir()
    holder = subprocess.Popen([sys.executable, "-c", HOLDER, str(out)], stdout=subprocess.PIPE,
                              env=SUBPROCESS_ENV)  # fmt: skip
    try:
        assert holder.stdout.readline().decode().strip() == "flock"
        assert main(["run", "--out", str(out), *_args()]) == 2
        err = capsys.readouterr().err
        assert f"host {socket.gethostname()}" in err and f"PID {holder.pid}" in err
        assert "in use by another segmpm run" in err and "Traceback" not in err
        assert main(["run", "--out", str(out), "--resume", *_args()]) == 2
        assert f"PID {holder.pid}" in capsys.readouterr().err
        assert not (out / "run.json").exists()
    finally:
        holder.kill()
        holder.wait()
    # the kernel released the lock of the killed process: the directory is usable at once
    assert main(["run", "--out", str(out), *_args("time.end=0.02",
                 "output.profile_times=[0.0]")]) == 0  # fmt: skip
    assert not (out / od.LOCK_NAME).exists()  # removed when the run ends


def test_lock_file_fallback_without_flock(tmp_path, monkeypatch):
    def no_flock(fd, op):
        raise OSError(errno.ENOLCK, "No locks available")

    monkeypatch.setattr(od.fcntl, "flock", no_flock)
    a = od.OutLock(tmp_path).acquire()
    assert a.mode == "file"
    rec = json.loads((tmp_path / od.LOCK_NAME).read_text())
    assert rec["host"] == socket.gethostname() and rec["pid"] == os.getpid() and rec["started"]
    with pytest.raises(od.LockedError) as exc:
        od.OutLock(tmp_path).acquire()
    assert f"PID {os.getpid()}" in str(exc.value) and str(tmp_path / od.LOCK_NAME) in str(exc.value)
    a.release()
    assert not (tmp_path / od.LOCK_NAME).exists()
    # a lock file of a dead process on this host is stale and taken over
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    stale = {"host": socket.gethostname(), "pid": dead.pid, "started": 1.0, "token": "x"}
    (tmp_path / od.LOCK_NAME).write_text(json.dumps(stale))
    b = od.OutLock(tmp_path).acquire()
    assert json.loads((tmp_path / od.LOCK_NAME).read_text())["pid"] == os.getpid()
    b.release()
    # another host's lock cannot be judged from here: it holds
    other = {**stale, "host": "elsewhere.example", "pid": 4242}
    (tmp_path / od.LOCK_NAME).write_text(json.dumps(other))
    with pytest.raises(od.LockedError, match="host elsewhere.example, PID 4242"):
        od.OutLock(tmp_path).acquire()
    # and the command line says so with exit 2
    assert main(["run", "--out", str(tmp_path), *_args()]) == 2


# ------------------------------------------------------------------------- 2. no silent overwrite


def test_a_completed_run_is_not_overwritten(tmp_path, capsys, tiny_reference):
    out = tmp_path / "run"
    assert main(["run", "--out", str(out), *_args("time.end=0.02")]) == 0
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    capsys.readouterr()
    assert main(["run", "--out", str(out), *_args()]) == 2
    err = capsys.readouterr().err
    assert "completed segmpm run" in err and "--overwrite" in err and "--resume" in err
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()} == before
    # --overwrite replaces it, stale snapshots and figures of the old run included
    (out / "fields").mkdir()
    (out / "fields" / "particles_0009.vtu").write_text("old")
    (out / "figures").mkdir()
    (out / "figures" / "profiles.png").write_text("old")
    assert main(["run", "--out", str(out), "--overwrite", *_args()]) == 0
    assert not (out / "fields").exists() and not (out / "figures").exists()
    _same_profiles(tiny_reference, out)


def test_foreign_files_are_refused_then_kept_by_overwrite(tmp_path, capsys, monkeypatch):
    (tmp_path / "notes.txt").write_text("mine")
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "x.csv").write_text("1,2")
    (tmp_path / "figures").mkdir()
    (tmp_path / "figures" / "sketch.png").write_text("mine too")
    monkeypatch.chdir(tmp_path)
    assert main(["run", "--out", ".", *_args("time.end=0.02")]) == 2
    err = capsys.readouterr().err
    assert "not segmpm's" in err and "notes.txt" in err and "--overwrite" in err
    assert not Path("run.json").exists()
    args = ["run", "--out", ".", "--overwrite", *_args("time.end=0.02", "output.figures=true")]
    assert main(args) == 0
    assert Path("notes.txt").read_text() == "mine" and Path("data/x.csv").read_text() == "1,2"
    assert Path("figures/sketch.png").read_text() == "mine too"
    assert Path("figures/profiles.png").exists()
    # a second --overwrite removes segmpm's files only
    assert main(args) == 0
    assert sorted(p.name for p in od.foreign_files(tmp_path)) == ["data", "notes.txt", "sketch.png"]
    od.remove_own_files(tmp_path)
    assert sorted(str(p.relative_to(tmp_path)) for p in tmp_path.rglob("*")) == [
        "data", "data/x.csv", "figures", "figures/sketch.png", "notes.txt"]  # fmt: skip


def test_overwrite_and_resume_exclude_each_other(tmp_path, capsys):
    assert main(["run", "--out", str(tmp_path), "--overwrite", "--resume"]) == 2
    assert "not allowed with" in capsys.readouterr().err


def test_own_files_patterns(tmp_path):
    for name in ["profiles.nc", "run.json", "config.toml", "compare.json", ".run.json.ab12.tmp",
                 "checkpoint/state.npz", "checkpoint/.state.npz.x1.tmp", "fields/particles.pvd",
                 "fields/particles_0000.vtu", "fields/.particles_0003.vtu.q.tmp.evtk.vtu",
                 "fields/.vtk.abc.vtu", "figures/profiles.png", "figures/compare.png",
                 "notes.md", "fields/mesh.vtu", "figures/other.png", "checkpoint/keep.txt",
                 "profiles.nc.bak", od.LOCK_NAME]:  # fmt: skip
        p = tmp_path / name
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text("x")
    own = {str(p.relative_to(tmp_path)) for p in od.own_files(tmp_path)}
    foreign = {str(p.relative_to(tmp_path)) for p in od.foreign_files(tmp_path)}
    assert foreign == {"notes.md", "fields/mesh.vtu", "figures/other.png",
                       "checkpoint/keep.txt", "profiles.nc.bak"}  # fmt: skip
    assert len(own) == 13 and not own & foreign and od.LOCK_NAME not in own


# ------------------------------------------------------------------------- 3. requeue-safe resume


def test_resume_starts_then_reports_complete(tmp_path, capsys, tiny_reference):
    cmd = ["run", "--out", str(tmp_path), "--resume", *_args()]
    assert main(cmd) == 0  # no checkpoint: starts
    assert "starting the run" in capsys.readouterr().err
    _same_profiles(tiny_reference, tmp_path)
    before = {p: p.stat().st_mtime_ns for p in tmp_path.rglob("*") if p.is_file()}
    t0 = time.perf_counter()
    assert main(cmd) == 0
    assert time.perf_counter() - t0 < 2.0
    assert "already complete" in capsys.readouterr().err
    assert {p: p.stat().st_mtime_ns for p in tmp_path.rglob("*") if p.is_file()} == before
    # keys that may differ: the thread count, the progress bar, the chunk bound
    assert main([*cmd, "--set", "grid.threads=1", "--set", "time.chunk_steps=7",
                 "--set", "output.progress=true"]) == 0  # fmt: skip
    assert "already complete" in capsys.readouterr().err
    # and without a configuration: OUT/config.toml
    assert main(["run", "--out", str(tmp_path), "--resume"]) == 0
    assert "already complete" in capsys.readouterr().err


def test_resume_with_a_changed_configuration_exits_2_naming_the_keys(tmp_path, capsys):
    assert main(["run", "--out", str(tmp_path), *_args("time.end=0.02")]) == 0
    capsys.readouterr()
    rc = main(["run", "--out", str(tmp_path), "--resume",
               *_args("time.end=0.02", "geometry.slope_deg=24.0", "time.cfl=0.3")])  # fmt: skip
    assert rc == 2
    err = capsys.readouterr().err
    assert "geometry.slope_deg = 24.0" in err and "time.cfl = 0.3" in err
    assert "2 key(s)" in err and "grid.threads" in err  # names what may differ
    assert _info(tmp_path)["status"] == "completed"


def test_resume_extends_a_completed_run_bit_for_bit(tmp_path, capsys, tiny_reference):
    # 0.05 is an output time, so the uninterrupted run stops there too
    assert main(["run", "--out", str(tmp_path), *_args("time.end=0.05")]) == 0
    assert list(_profiles(tmp_path)["time"].values) == [0.0, 0.02, 0.05]
    assert main(["run", "--out", str(tmp_path), "--resume", *_args()]) == 0
    assert "continuing the run" in capsys.readouterr().err
    _same_profiles(tiny_reference, tmp_path)
    assert "end = 0.1" in (tmp_path / "config.toml").read_text()
    # a shorter time.end than the run has reached is refused
    assert main(["run", "--out", str(tmp_path), "--resume", *_args("time.end=0.05")]) == 2
    assert "cannot be shortened" in capsys.readouterr().err


def _time_loop():
    """The generated kernel module of the run that ``segmpm run`` makes of TINY (the built-in
    preset): the run calls its ``advance``, the generic engine's compiled time loop (codegen keeps
    one module per dimension and law, so this is the module the run uses)."""
    from segmpm.config import DEFAULT_PRESET

    return make_sim(TINY, preset=DEFAULT_PRESET).kernels


def test_resume_after_an_interrupt_during_compile_starts_again(tmp_path, capsys, monkeypatch):
    """A SIGINT while the kernels compile (here: the zero-step call) stops the run at once, before
    the first checkpoint; the same command line with --resume then starts it."""
    loop = _time_loop()
    real = loop.advance

    def slow_compile(*a):
        if a[-1] == 0:  # the zero-step call that compiles or loads the kernels
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(5)  # the handler interrupts this at once
        return real(*a)

    slow_compile.signatures = real.signatures
    monkeypatch.setattr(loop, "advance", slow_compile)
    t0 = time.perf_counter()
    assert main(["run", "--out", str(tmp_path), *_args()]) == 130
    assert time.perf_counter() - t0 < 4
    err = capsys.readouterr().err
    assert "interrupted before the first step" in err
    assert not (tmp_path / "checkpoint" / "state.npz").exists()
    assert _info(tmp_path)["status"] == "interrupted"
    monkeypatch.setattr(loop, "advance", real)
    assert main(["run", "--out", str(tmp_path), "--resume", *_args("time.end=0.02")]) == 0


def test_requeue_after_sigkill_is_bit_identical(tmp_path, tiny_reference):
    """The batch-system pattern: the same command line with --resume after every SIGKILL (at a
    random moment after the first checkpoint) until it exits 0, then profiles.nc equals the
    uninterrupted run's exactly."""
    rng = np.random.default_rng(20240517)
    out = tmp_path / "run"
    cmd = ["run", "--out", str(out), "--resume", *_args("time.end=0.2",
           "output.profile_times=[0.0,0.02,0.05,0.1,0.2]")]  # fmt: skip
    ref = tmp_path / "ref"
    assert main(["run", "--out", str(ref), *cmd[4:]]) == 0
    kills = 0
    for _attempt in range(12):
        start = time.time()
        proc = _cli(*cmd, stderr=subprocess.DEVNULL)
        if kills < 3:
            # wait until this attempt is past its first checkpoint (run.json "running" rewritten)
            while time.time() - start < 300 and proc.poll() is None:
                info = out / "run.json"
                if info.exists() and info.stat().st_mtime >= start:
                    break
                time.sleep(0.02)
            time.sleep(rng.uniform(0.0, 1.5))
            if proc.poll() is None:
                proc.kill()
                kills += 1
        rc = proc.wait(timeout=600)
        if rc == 0:
            break
        assert rc == -signal.SIGKILL
    assert rc == 0 and kills >= 1
    _same_profiles(ref, out)
    assert _info(out)["status"] == "completed"


# ------------------------------------------------------------------------- 5. responsive run


def test_sigint_is_honoured_within_2_s_of_a_long_chunk(tmp_path):
    """time.chunk_steps = 10^7 would be one call of minutes: the calls are bounded in wall-clock
    time instead. Also: a second run into the busy directory names the running PID."""
    out = tmp_path / "run"
    args = _args("time.end=50", "time.chunk_steps=10000000", "output.checkpoint_interval=0",
                 "output.profile_times=[0.0,50.0]")  # fmt: skip
    proc = _cli("run", "--out", str(out), *args, stderr=subprocess.PIPE)
    try:
        deadline = time.time() + 300
        while time.time() < deadline and proc.poll() is None:
            if (out / "run.json").exists():
                break
            time.sleep(0.02)
        assert proc.poll() is None, proc.stderr.read().decode()
        time.sleep(1.5)  # well inside the loop
        r = subprocess.run([sys.executable, "-m", "segmpm.cli", "run", "--out", str(out), *args],
                           env=SUBPROCESS_ENV, capture_output=True, text=True, timeout=300)  # fmt: skip
        assert r.returncode == 2 and f"PID {proc.pid}" in r.stderr, r.stderr
        t0 = time.perf_counter()
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=60)
        took = time.perf_counter() - t0
    finally:
        if proc.poll() is None:
            proc.kill()
    err = proc.stderr.read().decode()
    assert rc == 130, err
    assert took < 2.5, took
    info = _info(out)
    assert info["status"] == "interrupted" and info["time"] > 0
    assert load_checkpoint(out / "checkpoint" / "state.npz")[1]["time"] == info["time"]


def test_compile_time_is_reported_apart(tmp_path, capsys, monkeypatch):
    import segmpm._cache

    loop = _time_loop()
    real = loop.advance

    def slow_compile(*a):
        if a[-1] == 0:
            time.sleep(1.5)
        return real(*a)

    slow_compile.signatures = []  # as in a fresh process
    monkeypatch.setattr(loop, "advance", slow_compile)
    # as in a fresh install: no compiled time loop in the (keyed) kernel cache
    monkeypatch.setattr(segmpm._cache, "KERNEL_CACHE", tmp_path / "empty-cache")
    assert main(["run", "--out", str(tmp_path / "a"), *_args("time.end=0.01",
                 "output.profile_times=[0.0]")]) == 0  # fmt: skip
    err = capsys.readouterr().err
    assert "compiling the 2-D kernels (first run only" in err
    info = _info(tmp_path / "a")
    assert info["compile_s"] >= 1.5
    assert info["wall_time_s"] < 1.0
    assert info["particle_steps_per_second"] == pytest.approx(
        info["steps"] * info["n_points"] / info["wall_time_s"]
    )
    # with the kernels in memory (or a warm cache) nothing is said
    monkeypatch.setattr(loop, "advance", real)
    assert main(["run", "--out", str(tmp_path / "b"), *_args("time.end=0.01",
                 "output.profile_times=[0.0]")]) == 0  # fmt: skip
    assert "compiling" not in capsys.readouterr().err
    # the end of the compile is reported too, after its start
    assert "kernels compiled in" in err, err
    assert err.index("compiling the 2-D kernels") < err.index("kernels compiled in")


def test_kernel_cache_detection(tmp_path, monkeypatch):
    """A compiled time loop in the kernel cache is found by its generated file's stem and its
    name (the MPM's ``advance`` apart from the column's ``advance_column``)."""
    import segmpm._cache

    monkeypatch.setattr(segmpm._cache, "KERNEL_CACHE", tmp_path)
    assert not simmod.kernel_cache_warm("kernels_d2_law1", "advance")
    (tmp_path / "gen_abc").mkdir()
    (tmp_path / "gen_abc" / "kernels_d2_law1.advance-393.py311.nbi").write_bytes(b"")
    assert simmod.kernel_cache_warm("kernels_d2_law1", "advance")
    assert not simmod.kernel_cache_warm("kernels_d2_law1", "advance_column")
    assert not simmod.kernel_cache_warm("kernels_d3_law1", "advance")


def test_steps_per_call_and_eta():
    f = simmod._steps_per_call
    assert f(64, 64, 0.001, 10**7) == 512  # grows at most 8-fold per call
    assert f(10**6, 10**5, 1.0, 10**7) == int(10**5 * simmod.CALL_SECONDS)  # ≈ 1 s of work
    assert f(100, 100, 0.01, 50) == 50  # never above time.chunk_steps
    assert f(5, 0, 0.0, 50) == 5 and f(1, 1, 100.0, 50) == 1
    assert simmod._eta(1.0, 0.25, 0.0, 10.0) == pytest.approx(30.0)
    assert simmod._eta(1.0, 0.5, 0.5, 10.0) is None
    bar = simmod._progress(False, 1.0, 0.0, 100)
    bar.start(0, 0.0)
    assert "ETA" in bar.postfix(0.5, 1000, 0.5) and "2,000 steps/s" in bar.postfix(0.5, 1000, 0.5)
