"""Simulation: builds the state from a configuration, runs the compiled loop in chunks, and calls
the output writers (profiles, VTK, checkpoints, figures, run.json) between chunks.

Python never loops over material points; it only decides when the compiled ``advance`` stops.
"""

from __future__ import annotations

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
    G_GX,
    G_GY,
    G_H,
    G_LX,
    G_NY,
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
EXIT_INTERRUPTED = 130


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
        self._interrupt: int | None = None
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
        status, idx, n = advance(
            st.x, st.v, st.C, st.mass, st.vol0, st.J, st.eps, st.sig, st.phi, st.gf, st.diag,
            st.s_int, st.g_int, st.gp, st.mp, st.sc, w["grid"], w["gv"],
            w["strip_start"], w["cursor"], w["order"], _bounds(w), w["flags"], w["x_old"], w["lg"],
            w["fw"], st.seg_prm, st.cg, st.seg_work, float(t_stop), int(max_steps),
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
        return d

    def _failure_message(self, status: int, idx: int) -> str:
        d = self._diagnostic(status, idx)
        where = (
            f" at point {idx} (x = {d['position'][0]:.6g} m, y = {d['position'][1]:.6g} m)"
            if idx >= 0
            else ""
        )
        extra = f"; non-finite: {', '.join(d['non_finite'])}" if d.get("non_finite") else ""
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

    def run(self, resume: bool = False, progress: bool | None = None) -> RunResult:
        """Run to ``time.end`` writing every output; returns a :class:`RunResult`.

        Numerical failure → status "failed" (exit code 3); SIGINT/SIGTERM → checkpoint and
        status "interrupted" (130). ``resume`` continues from ``out_dir/checkpoint``.
        """
        from .io.figures import plot_profiles
        from .io.profiles import ProfileWriter
        from .io.vtk import VTKSeries

        cfg = self.config
        out = self.out_dir
        out.mkdir(parents=True, exist_ok=True)
        ckpt_path = out / "checkpoint" / "state.npz"
        writer = ProfileWriter(out / "profiles.nc", self.edges, self._attrs())
        vtk = VTKSeries(out / "fields")
        if resume:
            self.load_checkpoint(ckpt_path)
            writer.restore(self.time)
            vtk.restore(self.time)
        else:
            write_text(out / "config.toml", cfg.to_toml())
            self._prime()
            self.save_checkpoint(ckpt_path)  # a last good state exists from the start
        show = cfg.output.progress if progress is None else progress
        end = cfg.time.end
        out_times = [t for t in cfg.output.profile_times if t <= end + 1e-12]
        written = set(writer.times)
        ckpt_dt = cfg.output.checkpoint_interval
        next_ckpt = (
            (math.floor(self.time / ckpt_dt + 1e-9) + 1) * ckpt_dt if ckpt_dt > 0 else math.inf
        )

        self._install_signals()
        bar = _progress(show, end, self.time, self.state.n)
        status, exit_code, failure = "running", EXIT_OK, None
        self._write_runinfo(status, None)
        try:
            for t_out in out_times:
                if (
                    t_out <= self.time + 1e-12
                    and t_out not in written
                    and abs(t_out - self.time) < 1e-12
                ):
                    self._output(t_out, writer, vtk)
                    written.add(t_out)
            while True:
                pending = [t for t in out_times if t > self.time + 1e-12]
                target = min([end, next_ckpt, *pending])
                if self.time >= end - 1e-15:
                    break
                status_code, idx, n = self.advance(target, cfg.time.chunk_steps)
                bar.update(self.time, self.steps, self.wall_time)
                if status_code != ST_OK:
                    raise SimulationError(
                        self._failure_message(status_code, idx), self._diagnostic(status_code, idx)
                    )
                if self._interrupt is not None:
                    raise KeyboardInterrupt
                if abs(self.time - target) <= 1e-12 * max(1.0, target):
                    if target in pending:
                        self._output(target, writer, vtk)
                    if target >= next_ckpt - 1e-12:
                        self.save_checkpoint(ckpt_path)
                        next_ckpt += ckpt_dt
                    self._write_runinfo("running", None)
            status = "completed"
            self.save_checkpoint(ckpt_path)
        except SimulationError as err:
            status, exit_code, failure = "failed", EXIT_NUMERICAL, err.diagnostic
            failure["message"] = str(err)
            print(f"segmpm: simulation failed: {err}", file=sys.stderr)
            print(f"segmpm: last good checkpoint kept in {ckpt_path}", file=sys.stderr)
        except KeyboardInterrupt:
            status, exit_code = "interrupted", EXIT_INTERRUPTED
            self.save_checkpoint(ckpt_path)
            print(f"segmpm: interrupted at t = {self.time:.6g} s; checkpoint in {ckpt_path}; "
                  f"continue with: segmpm run --resume --out {out}", file=sys.stderr)  # fmt: skip
        finally:
            bar.close()
            self._restore_signals()
        info = self._write_runinfo(status, failure)
        if status == "completed" and cfg.output.figures and writer.times:
            plot_profiles(writer.dataset(), out / "figures" / "profiles.png",
                          title=f"{cfg.scenario.kind}: depth profiles")  # fmt: skip
        return RunResult(status, exit_code, info)

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
        if self.config.output.fields:
            vtk.add(t, self.state, self.config.material.rheology == "nonlocal")

    def _write_runinfo(self, status: str, failure: dict[str, Any] | None) -> dict[str, Any]:
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
        write_json(self.out_dir / "run.json", info)
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

    def load_checkpoint(self, path: str | Path) -> None:
        """Restore the state saved by :meth:`save_checkpoint`."""
        arrays, meta = load_checkpoint(path)
        st = self.state
        for k in (*STATE_ARRAYS, "sc"):
            if arrays[k].shape != getattr(st, k).shape:
                raise ValueError(f"checkpoint {path}: array {k} has shape {arrays[k].shape}, "
                                 f"expected {getattr(st, k).shape} for this configuration")  # fmt: skip
            getattr(st, k)[...] = arrays[k]
        self._initial = meta["initial"]
        self.wall_time = float(meta.get("wall_time", 0.0))
        self._primed = True
        self._failed = None

    # --------------------------------------------------------------------------- signals
    def _install_signals(self) -> None:
        self._old_handlers = {}

        def handler(signum, frame):  # noqa: ARG001
            self._interrupt = signum

        for sig in (signal.SIGINT, signal.SIGTERM):
            try:
                self._old_handlers[sig] = signal.signal(sig, handler)
            except ValueError:  # not in the main thread
                pass

    def _restore_signals(self) -> None:
        for sig, h in getattr(self, "_old_handlers", {}).items():
            signal.signal(sig, h)
        self._old_handlers = {}


class _progress:
    """tqdm progress bar over simulated time with steps/s, particle-steps/s and ETA."""

    def __init__(self, show: bool, end: float, t0: float, n: int):
        self.n = n
        self.bar = None
        if show:
            from tqdm import tqdm

            self.bar = tqdm(total=end, initial=t0, unit="s", unit_scale=False, dynamic_ncols=True,
                            bar_format="{l_bar}{bar}| t={n:.4g}/{total:.4g} s [{elapsed}<{remaining}{postfix}]")  # fmt: skip
        self.t = t0

    def update(self, t: float, steps: int, wall: float) -> None:
        if self.bar is None:
            return
        self.bar.update(t - self.t)
        self.t = t
        if wall > 0:
            self.bar.set_postfix_str(
                f"{steps / wall:,.0f} steps/s, {steps * self.n / wall:.3g} particle-steps/s"
            )

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
