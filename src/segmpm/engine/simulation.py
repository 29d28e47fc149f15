"""A run on the dimension-generic engine (``geometry.dimension = 3``, or ``grid.engine =
"generic"`` in 2-D, the column model included).

:class:`EngineSimulation` is a :class:`segmpm.simulation.Simulation`: the same controller (chunked
calls of the compiled loop, outputs at the profile times, atomic checkpoints at k·Δt, resume,
signals, exit codes), with the state, the outputs and the checkpoints of the engine's records.
Outputs of a 3-D run in OUT_DIR, besides run.json, config.toml and checkpoint/:

* ``profiles.nc`` – depth profiles averaged over the length and the (modelled) width;
* ``cross_section.nc`` – maps across the channel, (time, y, z): ``velocity_x``, ``phi_small``,
  ``solid_fraction``, ``pressure``, ``shear_rate``, ``fluidity`` on cells of ``output.profile_bin`` in y and
  one grid cell in z, averaged along x;
* ``fields/`` – the points with their 3-D positions (VTK ``.vtu`` + ``.pvd``);
* ``figures/`` – the depth profiles and the cross-channel maps.
"""

from __future__ import annotations

import math
import time as _time
from pathlib import Path
from typing import Any

import numba
import numpy as np
import xarray as xr

from .. import __version__
from ..analysis.profiles import bin_edges
from ..config import Config, load_config
from ..io.checkpoint import load_checkpoint, save_checkpoint
from ..mpm.params import ST_DT_COLLAPSE, ST_OK, STATUS_TEXT
from ..simulation import Simulation, SimulationError, _estimate_message
from ..state import D_DRIVER, D_INERTIAL, D_PRESSURE, D_SHEAR_RATE
from .codegen import for_material
from .records import XY, YY, YZ
from .setup import EngineState, build, prime_clock

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


class EngineSimulation(Simulation):
    """A run of one configuration on the dimension-generic engine."""

    def __init__(self, config: Config | None = None, out_dir: str | Path | None = None):
        from .. import threads as _threads

        self.config = config if config is not None else load_config()
        self.out_dir = Path(out_dir if out_dir is not None else self.config.output.dir)
        self.dim = int(self.config.geometry.dimension)
        n_est = build_count(self.config)
        self.threads, self.threads_reason = _threads.resolve(self.config.grid.threads, n_est)
        self.engine: EngineState = build(self.config, self.dim, threads=self.threads)
        self.kernels = for_material(self.dim, self.engine.mat)
        self.state = self.engine  # what the controller's generic parts read (``n``)
        self._initial = self._invariants()
        self._primed = True  # build() primes the state
        self._failed: tuple[int, int] | None = None
        self.wall_time = 0.0
        self.compile_s = 0.0
        self._interrupt: int | None = None
        self._starting = False
        self.announce = False
        self._ckpt_time: float | None = None
        prm = self.engine.prm[0]
        grid_top = prm["origin"][1] + (prm["nodes"][1] - 1) * prm["h"]
        self.edges = bin_edges(grid_top, self.config.output.profile_bin)
        self._cross: list[tuple[float, dict[str, np.ndarray]]] = []

    # ------------------------------------------------------------------ stepping
    @property
    def clock(self) -> np.void:
        return self.engine.clock[0]

    @property
    def time(self) -> float:
        return float(self.clock["time"])

    @property
    def steps(self) -> int:
        return int(self.clock["step"])

    def _prime(self) -> None:
        pass  # build() primes the state

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

    def _compile_kernels(self) -> float:
        t0, wall = _time.perf_counter(), self.wall_time
        from .._cache import KERNEL_CACHE

        stem = Path(self.kernels.__file__).stem  # the step file of the run's law
        loop = "advance_column" if self.engine.nodes is not None else "advance"
        cold = not getattr(self.kernels, loop).signatures and not any(
            KERNEL_CACHE.rglob(f"{stem}.{loop}-*.nbi"))  # fmt: skip
        if cold:
            import sys

            print(f"segmpm: compiling the {self.dim}-D kernels (first run only, 1-3 minutes)",
                  file=sys.stderr, flush=True)  # fmt: skip
        try:
            self.advance(self.time, 0)
        finally:
            self.wall_time = wall
        took = _time.perf_counter() - t0
        if cold:
            import sys

            print(f"segmpm: kernels compiled in {took:.0f} s (cached for the next runs)",
                  file=sys.stderr, flush=True)  # fmt: skip
        return took

    # ------------------------------------------------------------------ diagnostics
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
        from ..segregation.diagnostics import segregation_index, species_centroids

        P = self.engine.points
        ys, yl = species_centroids(P.x[1], P.vol0, P.phi)
        return {"segregation_index": segregation_index(P.x[1], P.vol0, P.phi),
                "centroid_small": ys, "centroid_large": yl,
                "small_volume_drift": self.conservation()["small_volume_drift"]}  # fmt: skip

    # ------------------------------------------------------------------ outputs
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
        solid = np.bincount(i, weights=wm / cfg.material.grain_density, minlength=nb)
        area = self._area()
        out["solid_fraction"] = (np.where(solid > 0, solid / (area * np.diff(self.edges)), np.nan)
                                 if area else np.full(nb, np.nan))  # fmt: skip
        return out

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
        solid = np.bincount(cell, weights=wm / self.config.material.grain_density,
                            minlength=ny * nz).reshape(ny, nz)  # fmt: skip
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

    def _output(self, t: float, writer, vtk) -> None:
        from ..io.profiles import write_netcdf

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

    def _runinfo(self, status: str, failure: dict[str, Any] | None) -> dict[str, Any]:
        from ..threads import threading_layer

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

    # ------------------------------------------------------------------ checkpoints
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


def build_count(cfg: Config) -> int:
    """An estimate of the number of points (for the thread policy, before building)."""
    g = cfg.geometry
    s = cfg.grid.cell_size / cfg.grid.particles_per_cell
    if cfg.scenario.solver == "column":
        return max(2, round(g.depth / s))
    if cfg.scenario.kind == "chute":
        w = g.width / 2 if g.mirror else g.width
        return int(g.length * g.depth * (w if g.dimension == 3 else s) / s**3)
    if cfg.scenario.kind in ("box", "bar"):
        return int(g.length * g.depth * (g.width if g.dimension == 3 else s) / s**3)
    r = g.column_width
    return int((0.785 * r * r if g.dimension == 3 else r * s) * g.column_height / s**3)


__all__ = ["EngineSimulation", "SimulationError", "stress_ratio"]
