"""Simulation: builds the state from a configuration, runs the compiled loop in chunks, and calls
the output writers (profiles, VTK, checkpoints, figures, run.json) between chunks.

Python never loops over material points; it only decides when the compiled ``advance`` stops.
"""

from __future__ import annotations

import errno
import math
import signal
import sys
import time as _time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numba
import numpy as np

from . import __version__
from .analysis.profiles import bin_edges, depth_profiles
from .config import Config, load_config
from .io.atomic import write_json, write_text
from .io.checkpoint import load_checkpoint, save_checkpoint
from .mpm.params import (
    G_CFL,
    G_CFLOOR,
    G_DTMAX,
    G_DTMIN,
    G_GX,
    G_GY,
    G_H,
    G_LX,
    G_NY,
    G_VISC,
    G_Y0,
    S_DT,
    S_NFLU,
    S_NSEG,
    S_NUMAX,
    S_SMAX,
    S_STEP,
    S_TIME,
    ST_DT_COLLAPSE,
    ST_OK,
    STATUS_TEXT,
)
from .mpm.step import advance, prime
from .scenarios import build
from .state import D_SPEED, STATE_ARRAYS, State
from .threads import threading_layer

EXIT_OK = 0
EXIT_INVALID = 2
EXIT_NUMERICAL = 3
EXIT_WRITE = 4  # an output or checkpoint could not be written mid-run
EXIT_INTERRUPTED = 130

#: wall-clock seconds of work asked of one call of the compiled loop: Python (and so a SIGINT or
#: SIGTERM handler) runs only between calls, so this bounds the reaction to a signal
CALL_SECONDS = 1.0
#: steps of the first call of a run; later calls are sized from the measured step rate, never
#: above ``time.chunk_steps``
FIRST_CALL_STEPS = 64


def _steps_per_call(current: int, steps: int, seconds: float, limit: int) -> int:
    """Steps for the next call of the compiled loop: about :data:`CALL_SECONDS` of work at the
    rate of the last call (``steps`` in ``seconds``), growing at most 8-fold per call, between 1
    and ``limit`` (``time.chunk_steps``). The results do not depend on how a run is cut into
    calls (``tests/test_reliability.py``)."""
    if steps <= 0 or seconds <= 0.0:
        return max(1, min(limit, current))
    want = int(steps / seconds * CALL_SECONDS)
    return max(1, min(limit, want, 8 * max(current, steps)))


def kernel_cache_warm(loop: str = "step.advance") -> bool:
    """True when Numba's on-disk cache holds the compiled time loop ``loop`` (the MPM's
    ``step.advance`` or the column's ``column.advance_column``), i.e. the first call of this
    process loads it instead of compiling it."""
    from .mpm import step as _step

    root = numba.config.CACHE_DIR
    folder = Path(root) if root else Path(_step.__file__).parent / "__pycache__"
    try:
        return any(folder.rglob(f"{loop}-*.nbi"))
    except OSError:
        return False


def _bounds(work: dict[str, np.ndarray]) -> np.ndarray:
    """P2G's per-thread strip-run bounds, sized for the current Numba thread count."""
    nt = numba.get_num_threads()
    b = work.get("bounds")
    if b is None or b.shape[0] != nt + 1:
        b = work["bounds"] = np.zeros(nt + 1, dtype=np.int64)
    return b


class SimulationError(RuntimeError):
    """The run failed numerically; ``diagnostic`` says which quantity, where and when."""

    def __init__(self, message: str, diagnostic: dict[str, Any]):
        super().__init__(message)
        self.diagnostic = diagnostic


@dataclass
class RunResult:
    """Outcome of :meth:`Simulation.run` (also written to ``run.json``)."""

    status: str
    exit_code: int
    info: dict[str, Any] = field(default_factory=dict)


class Simulation:
    """A run of one configuration.

    >>> sim = Simulation(load_config(overrides=["time.end=0.01", "output.fields=false"]))
    >>> sim.advance_to(0.001)          # doctest: +SKIP
    >>> sim.profiles()["velocity_x"]   # doctest: +SKIP
    """

    def __new__(cls, config: Config | None = None, out_dir: str | Path | None = None):
        """Every run but ``grid.engine = "production"`` (2-D only) is on the dimension-generic
        engine (:class:`segmpm.engine.simulation.EngineSimulation`, the same controller)."""
        generic = config is None or config.grid.engine != "production"
        if cls is Simulation and generic:
            from .engine.simulation import EngineSimulation

            return super().__new__(EngineSimulation)
        return super().__new__(cls)

    def __init__(self, config: Config | None = None, out_dir: str | Path | None = None):
        self.config = config if config is not None else load_config()
        self.out_dir = Path(out_dir if out_dir is not None else self.config.output.dir)
        self.state: State = build(self.config)
        from . import threads as _threads

        #: thread count of the compiled loop and why (``grid.threads``; segmpm.threads)
        self.threads, self.threads_reason = _threads.resolve(self.config.grid.threads,
                                                             self.state.n)  # fmt: skip
        self._initial = self._invariants()
        self._primed = False
        self._failed: tuple[int, int] | None = None
        self.wall_time = 0.0
        #: seconds spent compiling (or loading) the kernels in this process's run, not part of
        #: ``wall_time`` (run.json ``compile_s``)
        self.compile_s = 0.0
        self._interrupt: int | None = None
        self._starting = False  # an interrupt raises KeyboardInterrupt at once (before step 1)
        #: print the estimated number of steps and wall time after the first call (the CLI sets it)
        self.announce = False
        self._ckpt_time: float | None = None  # time of the last checkpoint written or loaded
        grid_top = self.state.gp[G_Y0] + (self.state.gp[G_NY] - 1) * self.state.gp[G_H]
        self.edges = bin_edges(grid_top, self.config.output.profile_bin)

    # --------------------------------------------------------------------------- stepping
    @property
    def time(self) -> float:
        """Simulated time t, s."""
        return float(self.state.sc[S_TIME])

    @property
    def steps(self) -> int:
        """Time steps taken."""
        return int(self.state.sc[S_STEP])

    def _prime(self) -> None:
        if self._primed:
            return
        st = self.state
        if st.sc[S_STEP] == 0:
            prime(st.J, st.eps, st.sig, st.phi, st.gf, st.diag, st.mp, st.v)
            st.sc[S_SMAX] = float(np.max(st.diag[D_SPEED])) if st.n else 0.0
            st.sc[S_NUMAX] = float(np.max(st.diag[5])) if st.n else 0.0
        self._primed = True

    def advance(self, t_stop: float, max_steps: int) -> tuple[int, int, int]:
        """One call of the compiled loop; returns (status, point index, steps taken).

        After a failure status the state is not advanced again (a point outside the grid would
        make P2G write outside it): a second call raises :class:`SimulationError`; load a
        checkpoint to continue."""
        if self._failed is not None:
            status, idx = self._failed
            raise SimulationError(
                "the state failed at an earlier step and cannot be advanced: "
                + self._failure_message(status, idx),
                self._diagnostic(status, idx),
            )
        from .threads import KERNEL_LOCK

        with KERNEL_LOCK:
            numba.set_num_threads(self.threads)
            return self._advance_locked(t_stop, max_steps)

    def _advance_locked(self, t_stop: float, max_steps: int) -> tuple[int, int, int]:
        self._prime()
        st, w = self.state, self.state.work
        t0 = _time.perf_counter()
        if st.nodes is not None:
            from .column import advance_column

            status, idx, n = advance_column(
                st.x, st.v, st.mass, st.vol0, st.J, st.eps, st.sig, st.phi, st.gf, st.diag,
                st.s_int, st.g_int, st.nodes, w["seg_vol"], st.gp, st.mp, st.sc, w["fw"],
                st.seg_prm, st.cg, st.seg_work, float(t_stop), int(max_steps),
            )  # fmt: skip
        else:
            status, idx, n = advance(
                st.x, st.v, st.C, st.mass, st.vol0, st.J, st.eps, st.sig, st.phi, st.gf,
                st.diag, st.s_int, st.g_int, st.gp, st.mp, st.sc, w["grid"], w["gv"],
                w["strip_start"], w["cursor"], w["order"], _bounds(w), w["flags"], w["x_old"],
                w["lg"], w["fw"], st.seg_prm, st.cg, st.seg_work, float(t_stop), int(max_steps),
            )  # fmt: skip
        self.wall_time += _time.perf_counter() - t0
        if status != ST_OK:
            self._failed = (int(status), int(idx))
        return int(status), int(idx), int(n)

    def advance_to(self, t: float, chunk_steps: int | None = None) -> None:
        """Advance to time ``t`` exactly; raises :class:`SimulationError` on numerical failure."""
        chunk = chunk_steps or self.config.time.chunk_steps
        while self.time < t:
            status, idx, _ = self.advance(t, chunk)
            if status != ST_OK:
                raise SimulationError(
                    self._failure_message(status, idx), self._diagnostic(status, idx)
                )
            if self._interrupt is not None:
                return

    def _diagnostic(self, status: int, idx: int) -> dict[str, Any]:
        st = self.state
        d: dict[str, Any] = {
            "reason": STATUS_TEXT.get(status, str(status)),
            "time": self.time,
            "step": self.steps,
            "dt": float(st.sc[S_DT]),
        }
        if idx >= 0:
            d["point"] = int(idx)
            d["position"] = [float(st.x[0, idx]), float(st.x[1, idx])]
            d["velocity"] = [float(st.v[0, idx]), float(st.v[1, idx])]
            d["stress"] = [float(s) for s in st.sig[:, idx]]
            d["J"] = float(st.J[idx])
            bad = [
                name
                for name, arr in (("position", st.x[:, idx]), ("velocity", st.v[:, idx]),
                                  ("stress", st.sig[:, idx]), ("J", st.J[idx : idx + 1]))
                if not np.all(np.isfinite(arr))
            ]  # fmt: skip
            if bad:
                d["non_finite"] = bad
        if status == ST_DT_COLLAPSE:
            d["max_signal_speed"] = float(st.sc[S_SMAX])
            d["max_viscosity"] = float(st.sc[S_NUMAX])
            d.update(self._collapsed_step())
        return d

    def _estimate(self, end: float, steps: int, seconds: float) -> str:
        """The remaining steps at the last step's dt and the wall time at the rate of the first
        ``steps`` steps (``seconds``), with a warning above an hour."""
        dt = float(self.state.sc[S_DT])
        left = max(0.0, end - self.time)
        n_steps = int(math.ceil(left / dt)) if dt > 0 else 0
        wall = n_steps * seconds / steps
        return _estimate_message(n_steps, dt, self.state.n, 2, wall, steps)

    def _collapsed_step(self) -> dict[str, Any]:
        """The time step the control asked for when it fell below ``time.dt_min`` (the same
        limits as the compiled loop: dt_max, the Courant limit CFL h / max(c + |v|) with the
        wave-speed floor, the viscous limit C_ν h² / (2 ν_max)) and which limit set it."""
        gp, sc = self.state.gp, self.state.sc
        h = float(gp[G_H])
        dt, limit = float(gp[G_DTMAX]), "time.dt_max"
        smax = max(float(sc[S_SMAX]), float(gp[G_CFLOOR]))
        if smax > 0.0 and gp[G_CFL] * h / smax < dt:
            dt, limit = float(gp[G_CFL] * h / smax), "Courant limit CFL h / max(c + |v|)"
        if sc[S_NUMAX] > 0.0 and gp[G_VISC] * h * h / (2.0 * sc[S_NUMAX]) < dt:
            dt = float(gp[G_VISC] * h * h / (2.0 * sc[S_NUMAX]))
            limit = "viscous limit C_nu h^2 / (2 nu_max)"
        return {"dt_collapsed": dt, "dt_min": float(gp[G_DTMIN]), "dt_limit": limit}

    def _failure_message(self, status: int, idx: int) -> str:
        d = self._diagnostic(status, idx)
        where = (
            f" at point {idx} (x = {d['position'][0]:.6g} m, y = {d['position'][1]:.6g} m)"
            if idx >= 0
            else ""
        )
        extra = f"; non-finite: {', '.join(d['non_finite'])}" if d.get("non_finite") else ""
        if "dt_collapsed" in d:
            extra += (f"; dt = {d['dt_collapsed']:.3g} s < time.dt_min = {d['dt_min']:.3g} s "
                      f"({d['dt_limit']}, max(c + |v|) = {d['max_signal_speed']:.4g} m/s, "
                      f"max viscosity = {d['max_viscosity']:.3g} m²/s; last step "
                      f"dt = {d['dt']:.3g} s)")  # fmt: skip
        return f"{d['reason']}{where} at t = {d['time']:.6g} s, step {d['step']}{extra}"

    # --------------------------------------------------------------------------- diagnostics
    def _invariants(self) -> dict[str, float]:
        st = self.state
        return {
            "mass": float(np.sum(st.mass)),
            "small_volume": float(np.sum(st.vol0 * st.phi)),
            "momentum_x": float(np.sum(st.mass * st.v[0])),
            "momentum_y": float(np.sum(st.mass * st.v[1])),
        }

    def conservation(self) -> dict[str, float]:
        """Relative drift of total mass and small-grain volume, and the momentum change."""
        now, ini = self._invariants(), self._initial
        return {
            "mass_drift": (now["mass"] - ini["mass"]) / ini["mass"] if ini["mass"] else 0.0,
            "small_volume_drift": (
                (now["small_volume"] - ini["small_volume"]) / ini["small_volume"]
                if ini["small_volume"]
                else 0.0
            ),
            "momentum_x": now["momentum_x"],
            "momentum_y": now["momentum_y"],
            "momentum_x_initial": ini["momentum_x"],
            "momentum_y_initial": ini["momentum_y"],
            "gravity_x": float(self.state.gp[G_GX]),
            "gravity_y": float(self.state.gp[G_GY]),
        }

    def profiles(self) -> dict[str, np.ndarray]:
        """Depth profiles of the current state on the output bins."""
        cfg = self.config
        length = float(self.state.gp[G_LX]) if self.state.gp[G_LX] > 0 else None
        return depth_profiles(self.state, self.edges, cfg.material.solid_fraction,
                              cfg.material.grain_density, length,
                              cfg.material.rheology == "nonlocal")  # fmt: skip

    # --------------------------------------------------------------------------- run
    def _attrs(self) -> dict[str, str]:
        return {
            "title": "segmpm depth profiles",
            "segmpm_version": __version__,
            "scenario": self.config.scenario.kind,
            "configuration": self.config.to_toml(),
            "y_datum": "y = 0 at the no-slip base (top of the rough layer)",
        }

    def run(
        self, resume: bool = False, progress: bool | None = None, lock: bool = True
    ) -> RunResult:
        """Run to ``time.end`` writing every output; returns a :class:`RunResult`.

        Numerical failure → status "failed" (exit code 3); an output or checkpoint that cannot
        be written → status "failed" (exit code 4; the last complete checkpoint and outputs are
        kept, no temporary file is left); SIGINT/SIGTERM → checkpoint and status "interrupted"
        (130). ``resume`` continues from ``out_dir/checkpoint``. ``lock``: hold the lock on
        ``out_dir`` (``io.outdir.OutLock``) for the run, raising ``io.outdir.LockedError`` if
        another run holds it, and ``OutDirError`` if ``out_dir`` cannot be used; pass False when
        the caller holds it (the command line does).
        """
        if not lock:
            return self._run(resume, progress)
        from .io.outdir import OutLock, prepare_out_dir

        prepare_out_dir(self.out_dir)
        with OutLock(self.out_dir):
            return self._run(resume, progress)

    def _run(self, resume: bool, progress: bool | None) -> RunResult:
        from .io.figures import plot_profiles
        from .io.outdir import remove_stale_temporaries
        from .io.profiles import ProfileWriter
        from .io.vtk import VTKSeries

        cfg = self.config
        out = self.out_dir
        ckpt_path = out / "checkpoint" / "state.npz"
        show = cfg.output.progress if progress is None else progress
        end = cfg.time.end
        out_times = [t for t in cfg.output.profile_times if t <= end + 1e-12]
        ckpt_dt = cfg.output.checkpoint_interval
        bar = None
        status, exit_code, failure = "running", EXIT_OK, None
        keep = False  # True once the state is one to checkpoint on an interrupt
        # the handlers go in before the first compiled call: a first run compiles for minutes
        self._install_signals()
        try:
            self._starting = True  # until the first step, an interrupt stops the run at once
            try:
                remove_stale_temporaries(out)
                writer = ProfileWriter(out / "profiles.nc", self.edges, self._attrs())
                vtk = VTKSeries(out / "fields")
                if resume:
                    self.load_checkpoint(ckpt_path)
                    writer.restore(self.time)
                    vtk.restore(self.time)
                # (on resume: the configuration it continues with, e.g. a later time.end)
                write_text(out / "config.toml", cfg.to_toml())
                self.compile_s += self._compile_kernels()
            finally:
                self._starting = False
            if self._interrupt is not None:
                raise KeyboardInterrupt
            if not resume:
                self.save_checkpoint(ckpt_path)  # a last good state exists from the start
            keep = True
            written = set(writer.times)
            # checkpoint k at k·Δt_ckpt, a product rather than a running sum: the same times
            # in a fresh and a resumed run, and no drift onto (or off) an output time
            k_ckpt = math.floor(self.time / ckpt_dt + 1e-9) + 1 if ckpt_dt > 0 else 0
            next_ckpt = k_ckpt * ckpt_dt if ckpt_dt > 0 else math.inf
            bar = _progress(show, end, self.time, self.state.n)
            bar.start(self.steps, self.wall_time)
            self._write_runinfo(status, None)
            for t_out in out_times:
                if (
                    t_out <= self.time + 1e-12
                    and t_out not in written
                    and abs(t_out - self.time) < 1e-12
                ):
                    self._output(t_out, writer, vtk)
                    written.add(t_out)
            per_call = min(cfg.time.chunk_steps, FIRST_CALL_STEPS)
            announced = False
            while True:
                pending = [t for t in out_times if t > self.time + 1e-12]
                target = min([end, next_ckpt, *pending])
                if self.time >= end - 1e-15:
                    break
                t0 = _time.perf_counter()
                status_code, idx, n = self.advance(target, per_call)
                took = _time.perf_counter() - t0
                per_call = _steps_per_call(per_call, n, took, cfg.time.chunk_steps)
                if self.announce and not announced and status_code == ST_OK and n > 0:
                    announced = True
                    print(self._estimate(end, n, took), file=sys.stderr)
                bar.update(self.time, self.steps, self.wall_time)
                if status_code != ST_OK:
                    raise SimulationError(
                        self._failure_message(status_code, idx), self._diagnostic(status_code, idx)
                    )
                if self._interrupt is not None:
                    raise KeyboardInterrupt
                if abs(self.time - target) <= 1e-12 * max(1.0, target):
                    # every output time the state has reached (a checkpoint time within the
                    # tolerance of an output time must not make the output be skipped)
                    for t_out in pending:
                        if t_out <= self.time + 1e-12:
                            self._output(t_out, writer, vtk)
                    if target >= next_ckpt - 1e-12:
                        self.save_checkpoint(ckpt_path)
                        k_ckpt += 1
                        next_ckpt = k_ckpt * ckpt_dt
                    self._write_runinfo("running", None)
            self.save_checkpoint(ckpt_path)
            if cfg.output.figures and writer.times:
                plot_profiles(writer.dataset(), out / "figures" / "profiles.png",
                              title=f"{cfg.scenario.kind}: depth profiles")  # fmt: skip
            status = "completed"
        except SimulationError as err:
            status, exit_code, failure = "failed", EXIT_NUMERICAL, err.diagnostic
            failure["message"] = str(err)
            print(f"segmpm: simulation failed: {err}", file=sys.stderr)
            print(f"segmpm: last good checkpoint kept in {ckpt_path}", file=sys.stderr)
        except OSError as err:
            status, exit_code, failure = "failed", EXIT_WRITE, self._write_failure(err, ckpt_path)
        except KeyboardInterrupt:
            status, exit_code = "interrupted", EXIT_INTERRUPTED
            if keep:
                try:
                    self.save_checkpoint(ckpt_path)
                except OSError as err:
                    status, exit_code = "failed", EXIT_WRITE
                    failure = self._write_failure(err, ckpt_path)
                else:
                    print(f"segmpm: interrupted at t = {self.time:.6g} s; checkpoint in "
                          f"{ckpt_path}; continue with: segmpm run --resume --out {out}",
                          file=sys.stderr)  # fmt: skip
            else:
                print("segmpm: interrupted before the first step"
                      + (f"; the checkpoint in {ckpt_path} is unchanged" if resume else
                         " (no checkpoint yet: a --resume starts the run from the beginning)"),
                      file=sys.stderr)  # fmt: skip
        finally:
            if bar is not None:
                bar.close()
            self._restore_signals()
        if resume and not keep and exit_code == EXIT_INTERRUPTED:
            # stopped before the checkpoint was even loaded: run.json still describes it
            return RunResult(status, exit_code, self._runinfo(status, failure))
        try:
            info = self._write_runinfo(status, failure)
        except OSError as err:
            info = self._runinfo(status, failure)
            print(f"segmpm: error: {out / 'run.json'} could not be updated: {err}",
                  file=sys.stderr)  # fmt: skip
            if exit_code != EXIT_WRITE:
                exit_code = EXIT_WRITE
                info["status"] = "failed"
                info["failure"] = self._write_failure(err, ckpt_path, report=False)
        return RunResult(info["status"], exit_code, info)

    def _compile_kernels(self) -> float:
        """Compile the kernels (or load them from Numba's cache) before the first step: the
        initial state is primed (fresh run) and the time loop called for zero steps, which
        changes nothing. Returns the seconds taken (``compile_s`` of run.json), which are not
        part of the wall time of the loop; the first run of a fresh install says that it
        compiles (2–4 minutes)."""
        from .column import advance_column

        column = self.state.nodes is not None
        loop = advance_column if column else advance
        cold = not loop.signatures and not kernel_cache_warm(
            "column.advance_column" if column else "step.advance"
        )
        if cold:
            print("segmpm: compiling kernels (first run only, about 2-4 minutes)",
                  file=sys.stderr, flush=True)  # fmt: skip
        t0, wall = _time.perf_counter(), self.wall_time
        try:
            self.advance(self.time, 0)
        finally:
            self.wall_time = wall
        took = _time.perf_counter() - t0
        if cold:
            print(f"segmpm: kernels compiled in {took:.0f} s (cached for the next runs)",
                  file=sys.stderr, flush=True)  # fmt: skip
        return took

    def _write_failure(self, err: OSError, ckpt_path: Path, report: bool = True) -> dict[str, Any]:
        """The diagnostic of an output that could not be written (exit 4), printed if
        ``report``."""
        path = getattr(err, "path", None) or err.filename or "?"
        code = getattr(err, "code_name", None) or (
            errno.errorcode.get(err.errno) if isinstance(err.errno, int) else None
        )
        cause = err.strerror or str(err)
        message = f"cannot write {path}: {cause}" + (f" ({code})" if code else "")
        d: dict[str, Any] = {
            "reason": "output could not be written",
            "path": str(path),
            "errno": code,
            "cause": cause,
            "time": self.time,
            "step": self.steps,
            "last_checkpoint_time": self._ckpt_time,
            "message": message,
        }
        if report:
            kept = (
                f"the last complete checkpoint ({ckpt_path}, t = {self._ckpt_time:.6g} s)"
                if self._ckpt_time is not None
                else "no checkpoint was written yet; the outputs already written"
            )
            print(f"segmpm: error: {message}\nsegmpm: the run stopped at t = {self.time:.6g} s "
                  f"(step {self.steps}); {kept} and the outputs written before are kept. Once "
                  f"the cause is fixed, continue with: segmpm run --resume --out {self.out_dir}",
                  file=sys.stderr)  # fmt: skip
        return d

    def segregation_diagnostics(self) -> dict[str, float]:
        """Segregation index, species centroids and small-grain volume drift of the current state."""
        from .segregation.diagnostics import segregation_index, species_centroids

        st = self.state
        ys, yl = species_centroids(st.x[1], st.vol0, st.phi)
        return {
            "segregation_index": segregation_index(st.x[1], st.vol0, st.phi),
            "centroid_small": ys,
            "centroid_large": yl,
            "small_volume_drift": self.conservation()["small_volume_drift"],
        }

    def _output(self, t: float, writer, vtk) -> None:
        writer.add(t, self.profiles(), self.segregation_diagnostics())
        if self.config.output.fields and self.state.nodes is None:  # the column: profiles only
            vtk.add(t, self.state, self.config.material.rheology == "nonlocal")

    def _write_runinfo(self, status: str, failure: dict[str, Any] | None) -> dict[str, Any]:
        info = self._runinfo(status, failure)
        write_json(self.out_dir / "run.json", info)
        return info

    def _runinfo(self, status: str, failure: dict[str, Any] | None) -> dict[str, Any]:
        n = self.state.n
        info: dict[str, Any] = {
            "status": status,
            "segmpm_version": __version__,
            "scenario": self.config.scenario.kind,
            "time": self.time,
            "time_end": self.config.time.end,
            "steps": self.steps,
            "n_points": n,
            "wall_time_s": self.wall_time,
            "compile_s": self.compile_s,
            "particle_steps_per_second": (self.steps * n / self.wall_time)
            if self.wall_time > 0
            else None,
            "last_dt": float(self.state.sc[S_DT]),
            "conservation": self.conservation(),
            "segregation": self.segregation_diagnostics(),
            "threads": self.threads,
            "threads_policy": self.threads_reason,
            "threading_layer": threading_layer(),
            "concentration_steps": int(self.state.sc[S_NSEG]),
            "fluidity_updates": int(self.state.sc[S_NFLU]),
            "rheology": self.config.material.rheology,
        }
        if failure is not None:
            info["failure"] = failure
        return info

    # --------------------------------------------------------------------------- checkpoints
    def save_checkpoint(self, path: str | Path) -> None:
        """Atomically write everything needed to continue this run."""
        arrays = self.state.arrays()
        meta = {
            "time": self.time,
            "steps": self.steps,
            "wall_time": self.wall_time,
            "initial": self._initial,
            "configuration": self.config.to_dict(),
            "segmpm_version": __version__,
        }
        save_checkpoint(path, arrays, meta)
        self._ckpt_time = self.time

    def load_checkpoint(self, path: str | Path) -> None:
        """Restore the state saved by :meth:`save_checkpoint`."""
        arrays, meta = load_checkpoint(path)
        st = self.state
        keys = (*STATE_ARRAYS, "sc") + (("nodes",) if st.nodes is not None else ())
        for k in keys:
            if k not in arrays:
                raise ValueError(f"checkpoint {path}: no array {k} (a checkpoint of another "
                                 "solver?)")  # fmt: skip
            if arrays[k].shape != getattr(st, k).shape:
                raise ValueError(f"checkpoint {path}: array {k} has shape {arrays[k].shape}, "
                                 f"expected {getattr(st, k).shape} for this configuration")  # fmt: skip
            getattr(st, k)[...] = arrays[k]
        self._initial = meta["initial"]
        self.wall_time = float(meta.get("wall_time", 0.0))
        self._primed = True
        self._failed = None
        self._ckpt_time = self.time

    # --------------------------------------------------------------------------- signals
    def _install_signals(self) -> None:
        self._old_handlers = {}

        def handler(signum, frame):  # noqa: ARG001
            self._interrupt = signum
            if self._starting:  # compiling or loading: nothing to save yet, stop at once
                raise KeyboardInterrupt

        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                self._old_handlers[sig] = signal.signal(sig, handler)
            except ValueError:  # not in the main thread
                pass

    def _restore_signals(self) -> None:
        for sig, h in getattr(self, "_old_handlers", {}).items():
            signal.signal(sig, h)
        self._old_handlers = {}


def _estimate_message(n_steps: int, dt: float, n: int, dim: int, wall: float, steps: int) -> str:
    """The remaining ``n_steps`` at ``dt`` of ``n`` points in ``dim`` dimensions and their
    ``wall`` seconds at the rate of the first ``steps`` steps, with a warning above an hour."""
    msg = (f"segmpm: about {n_steps:,} more steps (dt = {dt:.3g} s, {n} points, {dim}-D), "
           f"estimated {_clock(wall)} of wall time at the rate of the first {steps} steps")  # fmt: skip
    if wall > 3600.0:
        msg += ("\nsegmpm: warning: this run is estimated to take more than an hour; check "
                "the resolved configuration (segmpm validate) - a file without `extends` "
                "starts from the schema's defaults, not the reduced-cost preset")  # fmt: skip
    return msg


def _eta(end: float, t: float, t_start: float, elapsed: float) -> float | None:
    """Seconds to ``end`` at the simulated-time rate measured since the loop started (at
    ``t_start``, ``elapsed`` wall seconds ago; the kernel compile is not in it), or None."""
    if elapsed <= 0.0 or t <= t_start:
        return None
    return max(0.0, end - t) * elapsed / (t - t_start)


def _clock(seconds: float) -> str:
    s = int(round(seconds))
    return (
        f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"
    )


class _progress:
    """tqdm progress bar over simulated time with steps/s, particle-steps/s and an ETA, all from
    the rates measured since :meth:`start` (after the kernels are compiled)."""

    def __init__(self, show: bool, end: float, t0: float, n: int):
        self.n = n
        self.end = end
        self.bar = None
        if show:
            from tqdm import tqdm

            self.bar = tqdm(total=end, initial=t0, unit="s", unit_scale=False, dynamic_ncols=True,
                            bar_format="{l_bar}{bar}| t={n:.4g}/{total:.4g} s [{elapsed}{postfix}]")  # fmt: skip
        self.t = t0
        self.t_start, self.steps_start, self.wall_start = t0, 0, 0.0
        self.clock_start = _time.perf_counter()

    def start(self, steps: int, wall: float) -> None:
        """The loop starts now, at ``steps`` steps and ``wall`` seconds of loop wall time."""
        self.steps_start, self.wall_start = steps, wall
        self.clock_start = _time.perf_counter()

    def postfix(self, t: float, steps: int, wall: float) -> str:
        parts = []
        busy = wall - self.wall_start
        done = steps - self.steps_start
        if busy > 0 and done > 0:
            parts.append(f"{done / busy:,.0f} steps/s, {done * self.n / busy:.3g} particle-steps/s")
        eta = _eta(self.end, t, self.t_start, _time.perf_counter() - self.clock_start)
        if eta is not None:
            parts.append(f"ETA {_clock(eta)}")
        return ", ".join(parts)

    def update(self, t: float, steps: int, wall: float) -> None:
        if self.bar is None:
            return
        self.bar.set_postfix_str(self.postfix(t, steps, wall), refresh=False)
        self.bar.update(t - self.t)  # redraws at most every 0.1 s (tqdm's mininterval)
        self.t = t

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
