"""Simulation: builds the engine's state from a configuration (segmpm.engine.setup), runs its
compiled loop in chunks, and calls the output writers (profiles, VTK, checkpoints, figures,
run.json) between chunks: chunked calls, outputs at the profile times, atomic checkpoints at
k·Δt, resume, signals, exit codes. One controller for 2-D and 3-D, the MPM and the column.

Python never loops over material points; it only decides when the compiled ``advance`` stops.
Outputs of a 3-D run in OUT_DIR, besides run.json, config.toml and checkpoint/:

* ``profiles.nc`` – depth profiles averaged over the length and the (modelled) width;
* ``cross_section.nc`` – maps across the channel, (time, y, z): ``velocity_x``, ``phi_small``,
  ``solid_fraction``, ``pressure``, ``shear_rate``, ``fluidity`` on cells of ``output.profile_bin`` in y and
  one grid cell in z, averaged along x;
* ``fields/`` – the points with their 3-D positions (VTK ``.vtu`` + ``.pvd``);
* ``figures/`` – the depth profiles and the cross-channel maps.
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
import xarray as xr

from . import __version__
from .analysis.profiles import bin_edges
from .config import Config, load_config
from .engine.codegen import for_material
from .engine.records import D_DRIVER, D_INERTIAL, D_PRESSURE, D_SHEAR_RATE, XY, YY, YZ
from .engine.setup import EngineState, build, prime_clock
from .io.atomic import write_json, write_text
from .io.checkpoint import load_checkpoint, save_checkpoint
from .mpm.params import ST_DT_COLLAPSE, ST_OK, STATUS_TEXT
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


def kernel_cache_warm(stem: str, loop: str) -> bool:
    """True when the kernel cache (``segmpm._cache.KERNEL_CACHE``) holds the compiled time loop
    ``loop`` (``advance`` or ``advance_column``) of the generated kernel file ``stem``, i.e. the
    first call of this process loads it instead of compiling it."""
    from ._cache import KERNEL_CACHE

    try:
        return any(KERNEL_CACHE.rglob(f"{stem}.{loop}-*.nbi"))
    except OSError:
        return False


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


CROSS_VARIABLES = {
    "velocity_x": ("m s-1", "downslope velocity u, averaged along x"),
    "phi_small": ("1", "small-grain volume fraction of the solid φ_s"),
    "solid_fraction": ("1", "solid volume fraction f"),
    "pressure": ("Pa", "elastic pressure p_e"),
    "shear_rate": ("s-1", "shear rate γ̇"),
    "fluidity": ("s-1", "granular fluidity g: the nonlocal state g, or γ̇/μ of a local run"),
}


def stress_ratio(sig: np.ndarray, p: np.ndarray) -> np.ndarray:
    """μ = √(½ s:s)/p_e of stresses (NE, N) in the engine's order (0 where p_e ≤ 0)."""
    tr = (sig[0] + sig[1] + sig[2]) / 3.0
    s2 = sum((sig[a] - tr) ** 2 for a in range(3)) + 2.0 * sum(sig[a] ** 2 for a in
                                                                range(3, sig.shape[0]))  # fmt: skip
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(p > 0, np.sqrt(0.5 * s2) / np.where(p > 0, p, 1.0), 0.0)


class Simulation:
    """A run of one configuration on the engine (2-D or 3-D, the MPM or the column model).

    >>> sim = Simulation(load_config(overrides=["time.end=0.01", "output.fields=false"]))
    >>> sim.advance_to(0.001)          # doctest: +SKIP
    >>> sim.profiles()["velocity_x"]   # doctest: +SKIP
    """

    def __init__(self, config: Config | None = None, out_dir: str | Path | None = None):
        from . import threads as _threads

        self.config = config if config is not None else load_config()
        self.out_dir = Path(out_dir if out_dir is not None else self.config.output.dir)
        self.dim = int(self.config.geometry.dimension)
        n_est = build_count(self.config)
        self.threads, self.threads_reason = _threads.resolve(self.config.grid.threads, n_est)
        #: points, grid and records of the run (segmpm.engine.setup), and its compiled kernels
        self.engine: EngineState = build(self.config, self.dim, threads=self.threads)
        self.kernels = for_material(self.dim, self.engine.mat)
        self._initial = self._invariants()
        self._failed: tuple[int, int] | None = None
        #: seconds in the compiled loop (run.json ``wall_time_s``)
        self.wall_time = 0.0
        #: seconds spent compiling (or loading) the kernels in this process's run, not part of
        #: ``wall_time`` (run.json ``compile_s``)
        self.compile_s = 0.0
        self._interrupt: int | None = None
        self._starting = False  # an interrupt raises KeyboardInterrupt at once (before step 1)
        #: print the estimated number of steps and wall time after the first call (the CLI sets it)
        self.announce = False
        self._ckpt_time: float | None = None  # time of the last checkpoint written or loaded
        prm = self.engine.prm[0]
        grid_top = prm["origin"][1] + (prm["nodes"][1] - 1) * prm["h"]
        self.edges = bin_edges(grid_top, self.config.output.profile_bin)
        self._cross: list[tuple[float, dict[str, np.ndarray]]] = []

    # --------------------------------------------------------------------------- stepping
    @property
    def clock(self) -> np.void:
        """The CLOCK record (time, step, Δt, the subcycle clocks, the last step's maxima)."""
        return self.engine.clock[0]

    @property
    def time(self) -> float:
        """Simulated time t, s."""
        return float(self.clock["time"])

    @property
    def steps(self) -> int:
        """Time steps taken."""
        return int(self.clock["step"])

    def prime(self) -> None:
        """Derive the initial state again from points edited before the first step (a launched,
        pre-compacted or pre-sheared layer): the stress σ(ε^e, J), the diagnostics (p_e, γ̇, I,
        S, c + |v|, ν) and the first step's time-step bound from them. Raises
        RuntimeError once the run has stepped (its state is then the loop's)."""
        if self.steps:
            raise RuntimeError(f"prime() derives the initial state; the run has already taken "
                               f"{self.steps} steps")  # fmt: skip
        e = self.engine
        self.kernels.prime(e.points, e.mat)
        prime_clock(e)
        self._initial = self._invariants()

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
        e = self.engine
        numba.set_num_threads(self.threads)
        if e.grid.bounds.shape[0] != self.threads + 1:
            # P2G's per-thread slab runs, sized for the thread count of this call (it may have
            # been changed since set-up, as the bench does): results do not depend on it
            e.grid = e.grid._replace(bounds=np.zeros(self.threads + 1, dtype=np.int64))
        t0 = _time.perf_counter()
        if e.nodes is not None:  # the column model
            status, idx, n = self.kernels.advance_column(
                e.points, e.seg_points, e.nodes, e.grid, e.prm, e.mat, e.clock, e.seg,
                float(t_stop), int(max_steps))  # fmt: skip
        else:
            status, idx, n = self.kernels.advance(e.points, e.grid, e.prm, e.mat, e.clock, e.seg,
                                                  float(t_stop), int(max_steps))  # fmt: skip
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

    # --------------------------------------------------------------------------- diagnostics
    def _diagnostic(self, status: int, idx: int) -> dict[str, Any]:
        P = self.engine.points
        c = self.clock
        d: dict[str, Any] = {"reason": STATUS_TEXT.get(status, str(status)), "time": self.time,
                             "step": self.steps, "dt": float(c["dt"])}  # fmt: skip
        if idx >= 0:
            d["point"] = int(idx)
            d["position"] = [float(v) for v in P.x[:, idx]]
            d["velocity"] = [float(v) for v in P.v[:, idx]]
            d["stress"] = [float(s) for s in P.sig[:, idx]]
            d["J"] = float(P.J[idx])
            bad = [name for name, arr in (("position", P.x[:, idx]), ("velocity", P.v[:, idx]),
                                          ("stress", P.sig[:, idx]), ("J", P.J[idx:idx + 1]))
                   if not np.all(np.isfinite(arr))]  # fmt: skip
            if bad:
                d["non_finite"] = bad
        if status == ST_DT_COLLAPSE:
            d["max_signal_speed"] = float(c["smax"])
            d["max_viscosity"] = float(c["numax"])
            d.update(self._collapsed_step())
        return d

    def _collapsed_step(self) -> dict[str, Any]:
        prm, c = self.engine.prm[0], self.clock
        h = float(prm["h"])
        dt, limit = float(prm["dt_max"]), "time.dt_max"
        smax = max(float(c["smax"]), float(prm["c_floor"]))
        if smax > 0.0 and prm["cfl"] * h / smax < dt:
            dt, limit = float(prm["cfl"] * h / smax), "Courant limit CFL h / max(c + |v|)"
        if c["numax"] > 0.0 and prm["visc"] * h * h / (2.0 * c["numax"]) < dt:
            dt = float(prm["visc"] * h * h / (2.0 * c["numax"]))
            limit = "viscous limit C_nu h^2 / (2 nu_max)"
        return {"dt_collapsed": dt, "dt_min": float(prm["dt_min"]), "dt_limit": limit}

    def _failure_message(self, status: int, idx: int) -> str:
        d = self._diagnostic(status, idx)
        where = ""
        if idx >= 0:
            where = f" at point {idx} (x = " + ", ".join(f"{v:.6g}" for v in d["position"]) + " m)"
        extra = f"; non-finite: {', '.join(d['non_finite'])}" if d.get("non_finite") else ""
        if "dt_collapsed" in d:
            extra += (f"; dt = {d['dt_collapsed']:.3g} s < time.dt_min = {d['dt_min']:.3g} s "
                      f"({d['dt_limit']})")  # fmt: skip
        return f"{d['reason']}{where} at t = {d['time']:.6g} s, step {d['step']}{extra}"

    def _estimate(self, end: float, steps: int, seconds: float) -> str:
        dt = float(self.clock["dt"])
        left = max(0.0, end - self.time)
        n_steps = int(math.ceil(left / dt)) if dt > 0 else 0
        wall = n_steps * seconds / steps
        return _estimate_message(n_steps, dt, self.engine.n, self.dim, wall, steps)

    def _invariants(self) -> dict[str, float]:
        P = self.engine.points
        out = {"mass": float(np.sum(P.mass)), "small_volume": float(np.sum(P.vol0 * P.phi))}
        for a, name in enumerate("xyz"[: self.dim]):
            out[f"momentum_{name}"] = float(np.sum(P.mass * P.v[a]))
        return out

    def conservation(self) -> dict[str, float]:
        now, ini = self._invariants(), self._initial
        out = {
            "mass_drift": (now["mass"] - ini["mass"]) / ini["mass"] if ini["mass"] else 0.0,
            "small_volume_drift": ((now["small_volume"] - ini["small_volume"])
                                   / ini["small_volume"] if ini["small_volume"] else 0.0),
        }  # fmt: skip
        for k in now:
            if k.startswith("momentum"):
                out[k] = now[k]
                out[k + "_initial"] = ini[k]
        return out

    def segregation_diagnostics(self) -> dict[str, float]:
        from .segregation.diagnostics import segregation_index, species_centroids

        P = self.engine.points
        ys, yl = species_centroids(P.x[1], P.vol0, P.phi)
        return {"segregation_index": segregation_index(P.x[1], P.vol0, P.phi),
                "centroid_small": ys, "centroid_large": yl,
                "small_volume_drift": self.conservation()["small_volume_drift"]}  # fmt: skip

    # --------------------------------------------------------------------------- outputs
    def _area(self) -> float | None:
        """The footprint (x–z area) over which the profiles' solid fraction is taken."""
        prm = self.engine.prm[0]
        if not prm["periodic_x"]:
            return None
        area = float(prm["length_x"])
        if self.dim == 3:
            area *= float(prm["zhi"] - prm["zlo"])
        return area

    def profiles(self) -> dict[str, np.ndarray]:
        """Depth profiles of the current state, averaged over x and the modelled width."""
        P = self.engine.points
        cfg = self.config
        nb = len(self.edges) - 1
        idx = np.searchsorted(self.edges, P.x[1], side="right") - 1
        ok = (idx >= 0) & (idx < nb)
        i = idx[ok]
        wv = P.vol0[ok]
        wm = P.mass[ok]

        def avg(values: np.ndarray, w: np.ndarray) -> np.ndarray:
            num = np.bincount(i, weights=w * values[ok], minlength=nb)
            den = np.bincount(i, weights=w, minlength=nb)
            with np.errstate(invalid="ignore", divide="ignore"):
                return np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)

        mu, g = self._fluidity()
        out = {
            "phi_small": avg(P.phi, wv),
            "velocity_x": avg(P.v[0], wm),
            "velocity_y": avg(P.v[1], wm),
            "pressure": avg(P.diag[D_PRESSURE], wv),
            "inertial_number": avg(P.diag[D_INERTIAL], wv),
            "shear_rate": avg(P.diag[D_SHEAR_RATE], wv),
            "segregation_driver": avg(P.diag[D_DRIVER], wv),
            "shear_stress": avg(P.sig[XY], wv),
            "normal_stress": avg(-P.sig[YY], wv),
            "stress_ratio": avg(mu, wv),
            "fluidity": avg(g, wv),
        }
        solid = self._solid_per_bin(P.x[1], P.mass / cfg.material.grain_density)
        area = self._area()
        out["solid_fraction"] = (np.where(solid > 0, solid / (area * np.diff(self.edges)), np.nan)
                                 if area else np.full(nb, np.nan))  # fmt: skip
        return out

    def _slab_overlaps(self, y: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """Which y bins each point's slab [y − Δ/2, y + Δ/2] covers, and by what fraction.

        Δ is the lattice spacing of the points along y, h / n_y. Charging the whole solid volume
        of a point to the bin of its centre aliases whenever Δ does not divide the bin (with 3
        points per 1 mm cell in 0.5 mm bins the bins hold 2 and 1 points in turn, and f reads
        0.8, 0.4, ...); the slab gives the lattice's f in every bin it fills. Returns, for each
        bin offset, the bin of every point and the fraction of its slab in that bin (0 outside
        the bins)."""
        e = self.edges
        nb = len(e) - 1
        width = float(e[1] - e[0])
        d = self.config.grid.point_spacing(self.dim)[1]
        lo, hi = y - 0.5 * d, y + 0.5 * d
        first = np.floor((lo - e[0]) / width).astype(np.int64)
        out = []
        for j in range(int(np.ceil(d / width)) + 1):
            b = first + j
            frac = (np.minimum(hi, e[0] + (b + 1) * width) - np.maximum(lo, e[0] + b * width)) / d
            inside = (b >= 0) & (b < nb) & (frac > 0)
            out.append((np.where(inside, b, 0), np.where(inside, frac, 0.0)))
        return out

    def _solid_per_bin(self, y: np.ndarray, solid: np.ndarray, nz: int = 1,
                       iz: np.ndarray | None = None) -> np.ndarray:  # fmt: skip
        """Solid volume per y bin (or per y bin × z cell), each point spread over its slab."""
        nb = len(self.edges) - 1
        tot = np.zeros(nb * nz)
        for b, frac in self._slab_overlaps(y):
            cell = b * nz + (iz if iz is not None else 0)
            tot += np.bincount(cell, weights=solid * frac, minlength=nb * nz)
        return tot

    def _fluidity(self) -> tuple[np.ndarray, np.ndarray]:
        """(μ, g) of every point: the stress ratio and the fluidity (the state g of a nonlocal
        run, γ̇/μ of a local one; as analysis.profiles.point_fluidity)."""
        P = self.engine.points
        mu = stress_ratio(P.sig, P.diag[D_PRESSURE])
        if self.config.material.rheology == "nonlocal":
            return mu, P.gf.copy()
        with np.errstate(invalid="ignore", divide="ignore"):
            return mu, np.where(mu > 0, P.diag[D_SHEAR_RATE] / np.where(mu > 0, mu, 1.0), 0.0)

    def cross_section(self) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
        """Maps across the channel (y bins × z cells), averaged along x: (y, z, fields)."""
        P = self.engine.points
        prm = self.engine.prm[0]
        h = float(prm["h"])
        zlo, zhi = float(prm["zlo"]), float(prm["zhi"])
        nz = max(1, int(round((zhi - zlo) / h)))
        ze = zlo + np.arange(nz + 1) * (zhi - zlo) / nz
        ny = len(self.edges) - 1
        iy = np.searchsorted(self.edges, P.x[1], side="right") - 1
        iz = np.clip(np.searchsorted(ze, P.x[2], side="right") - 1, 0, nz - 1)
        ok = (iy >= 0) & (iy < ny)
        cell = iy[ok] * nz + iz[ok]
        wv = P.vol0[ok]
        wm = P.mass[ok]

        def avg(values: np.ndarray, w: np.ndarray) -> np.ndarray:
            num = np.bincount(cell, weights=w * values[ok], minlength=ny * nz)
            den = np.bincount(cell, weights=w, minlength=ny * nz)
            with np.errstate(invalid="ignore", divide="ignore"):
                r = np.where(den > 0, num / np.where(den > 0, den, 1.0), np.nan)
            return r.reshape(ny, nz)

        fields = {
            "velocity_x": avg(P.v[0], wm),
            "phi_small": avg(P.phi, wv),
            "pressure": avg(P.diag[D_PRESSURE], wv),
            "shear_rate": avg(P.diag[D_SHEAR_RATE], wv),
            "fluidity": avg(self._fluidity()[1], wv),
        }
        solid = self._solid_per_bin(P.x[1], P.mass / self.config.material.grain_density, nz,
                                    iz).reshape(ny, nz)  # fmt: skip
        vol = float(prm["length_x"]) * np.diff(self.edges)[:, None] * np.diff(ze)[None, :]
        fields["solid_fraction"] = np.where(solid > 0, solid / vol, np.nan)
        yc = 0.5 * (self.edges[1:] + self.edges[:-1])
        zc = 0.5 * (ze[1:] + ze[:-1])
        return yc, zc, fields

    def _cross_dataset(self) -> xr.Dataset:
        yc, zc, _ = self.cross_section()
        times = [t for t, _ in self._cross]
        data = {}
        for k, (units, long) in CROSS_VARIABLES.items():
            arr = np.stack([f[k] for _, f in self._cross]) if self._cross else np.zeros(
                (0, len(yc), len(zc)))  # fmt: skip
            data[k] = (("time", "y", "z"), arr, {"units": units, "long_name": long})
        return xr.Dataset(data, coords={"time": ("time", np.array(times), {"units": "s"}),
                                        "y": ("y", yc, {"units": "m"}),
                                        "z": ("z", zc, {"units": "m"})},
                          attrs=self._attrs())  # fmt: skip

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
            bar = _progress(show, end, self.time, self.engine.n)
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
        """Compile the kernels (or load them from the kernel cache) before the first step: the
        time loop is called for zero steps, which changes nothing. Returns the seconds taken
        (``compile_s`` of run.json), which are not part of the wall time of the loop; a cold
        compile says that it compiles and, when done, how long it took."""
        t0, wall = _time.perf_counter(), self.wall_time
        stem = Path(self.kernels.__file__).stem  # the step file of the run's law
        loop = "advance_column" if self.engine.nodes is not None else "advance"
        cold = not getattr(self.kernels, loop).signatures and not kernel_cache_warm(stem, loop)
        if cold:
            print(f"segmpm: compiling the {self.dim}-D kernels (first run only, 1-3 minutes)",
                  file=sys.stderr, flush=True)  # fmt: skip
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

    def _output(self, t: float, writer, vtk) -> None:
        from .io.profiles import write_netcdf

        writer.add(t, self.profiles(), self.segregation_diagnostics())
        P = self.engine.points
        if self.dim == 3 and self.config.scenario.kind == "chute":
            self._cross = [(tt, f) for tt, f in self._cross if tt < t - 1e-12]
            self._cross.append((t, self.cross_section()[2]))
            write_netcdf(self.out_dir / "cross_section.nc", self._cross_dataset())
        if self.config.output.fields and self.engine.nodes is None:  # the column: profiles only
            mu, g = self._fluidity()
            data = {"velocity_x": P.v[0], "velocity_y": P.v[1],
                    "velocity_z": P.v[2] if self.dim == 3 else np.zeros(self.engine.n),
                    "phi_small": P.phi, "pressure": P.diag[D_PRESSURE],
                    "shear_rate": P.diag[D_SHEAR_RATE], "inertial_number": P.diag[D_INERTIAL],
                    "segregation_driver": P.diag[D_DRIVER], "sigma_xy": P.sig[XY],
                    "sigma_yy": P.sig[YY], "J": P.J, "stress_ratio": mu,
                    "fluidity": g}  # fmt: skip
            if self.dim == 3:
                data["sigma_yz"] = P.sig[YZ]
            z = P.x[2] if self.dim == 3 else np.zeros(self.engine.n)
            vtk.add_points(t, P.x[0], P.x[1], z, data)

    def _restore_cross(self, until: float) -> None:
        path = self.out_dir / "cross_section.nc"
        if not path.exists():
            return
        with xr.open_dataset(path, engine="h5netcdf") as ds:
            ds = ds.load()
        for i, t in enumerate(ds["time"].values):
            if t <= until + 1e-12:
                self._cross.append((float(t), {k: ds[k].values[i] for k in CROSS_VARIABLES}))

    def _write_runinfo(self, status: str, failure: dict[str, Any] | None) -> dict[str, Any]:
        info = self._runinfo(status, failure)
        write_json(self.out_dir / "run.json", info)
        return info

    def _runinfo(self, status: str, failure: dict[str, Any] | None) -> dict[str, Any]:
        n = self.engine.n
        info: dict[str, Any] = {
            "status": status, "segmpm_version": __version__,
            "scenario": self.config.scenario.kind, "dimension": self.dim,
            "engine": "generic", "time": self.time, "time_end": self.config.time.end,
            "steps": self.steps, "n_points": n, "wall_time_s": self.wall_time,
            "compile_s": self.compile_s,
            "particle_steps_per_second": (self.steps * n / self.wall_time
                                          if self.wall_time > 0 else None),
            "last_dt": float(self.clock["dt"]), "conservation": self.conservation(),
            "segregation": self.segregation_diagnostics(), "threads": self.threads,
            "threads_policy": self.threads_reason, "threading_layer": threading_layer(),
            "concentration_steps": int(self.clock["nseg"]),
            "fluidity_updates": int(self.clock["nflu"]),
            "rheology": self.config.material.rheology, "solver": self.config.scenario.solver,
        }  # fmt: skip
        if failure is not None:
            info["failure"] = failure
        return info

    # --------------------------------------------------------------------------- checkpoints
    def save_checkpoint(self, path: str | Path) -> None:
        arrays = self.engine.arrays()
        meta = {"time": self.time, "steps": self.steps, "wall_time": self.wall_time,
                "initial": self._initial, "configuration": self.config.to_dict(),
                "segmpm_version": __version__, "dimension": self.dim}  # fmt: skip
        save_checkpoint(path, arrays, meta)
        self._ckpt_time = self.time

    def load_checkpoint(self, path: str | Path) -> None:
        arrays, meta = load_checkpoint(path)
        for k, target in self.engine.arrays().items():
            if k not in arrays or arrays[k].shape != target.shape:
                raise ValueError(f"checkpoint {path}: array {k} missing or of another shape "
                                 "(a checkpoint of another configuration or dimension?)")  # fmt: skip
            target[...] = arrays[k]
        self._initial = meta["initial"]
        self.wall_time = float(meta.get("wall_time", 0.0))
        self._failed = None
        self._ckpt_time = self.time
        self._cross = []
        self._restore_cross(self.time)

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


def build_count(cfg: Config) -> int:
    """An estimate of the number of points (for the thread policy, before building)."""
    g = cfg.geometry
    sp = cfg.grid.point_spacing(g.dimension)
    if cfg.scenario.solver == "column":
        return max(2, round(g.depth / sp[1]))
    cell = math.prod(sp)  # the area (2-D) or volume (3-D) of one point
    if cfg.scenario.kind == "chute":
        w = g.width / 2 if g.mirror else g.width
        return int(g.length * g.depth * (w if g.dimension == 3 else 1) / cell)
    if cfg.scenario.kind in ("box", "bar"):
        return int(g.length * g.depth * (g.width if g.dimension == 3 else 1) / cell)
    r = g.column_width
    return int((0.785 * r * r if g.dimension == 3 else r) * g.column_height / cell)


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
