"""``segmpm compare OUT_DIR REFERENCE.csv``: error norms of a run's depth profiles against a reference.

Definitions (the public interface of ``compare``; README, "Command line"):

* The reference CSV has the columns ``time_s, y_m, phi_small, velocity_x`` (extra columns are
  ignored; lines whose first non-blank character is ``#`` and blank lines are skipped; an empty
  cell or ``nan`` is a missing value of ``phi_small``/``velocity_x``, never of ``time_s``/``y_m``).
* Times: ``--times`` if given, else every time present in both the run and the reference; two times
  match when they differ by at most :data:`TIME_TOL` = 1e-6 s.
* At each time and for each of ``phi_small`` and ``velocity_x`` separately, the run's profile with
  its NaN (empty) bins dropped is interpolated linearly (``numpy.interp``) at the reference heights
  ``y_m + y_offset``, over the **whole depth of the reference**: a reference row above the run's
  highest (or below its lowest) non-empty bin centre is compared with the run's value there
  (the profile extended as a constant: a run whose surface lies lower than the reference's is
  charged for the missing layer). Δ = run − reference. The same norms restricted to the rows
  within the run's bins are reported with the suffix ``_overlap``, and ``n_phi_outside``,
  ``n_velocity_outside`` count the rows outside.
* ``phi_rms`` = sqrt(mean Δφ_s²), ``phi_max`` = max |Δφ_s|.
* ``segregation_skill`` = 1 − phi_rms / phi_rms_mixed, with phi_rms_mixed the RMS of
  φ_s,ref − φ₀ (φ₀: the run's initial, well-mixed small-grain fraction, ``mixture.
  phi_small_initial`` of its configuration) over the same rows: 1 is a perfect prediction, 0 is
  no better than predicting no segregation, negative is worse (null when the reference is still
  mixed, phi_rms_mixed ≤ 1e-9).
* Surface velocity u_s of a profile: the mean of ``velocity_x`` over its :data:`SURFACE_BINS` = 2
  highest bins (rows) with a finite velocity (one bin if only one has data). Computed the same way
  for the reference (its rows at that time) and for the run (its bins).
* ``u_rms_rel`` = sqrt(mean Δu²) / |u_s of the reference| (null if |u_s,ref| ≤ 1e-12 m/s);
  ``u_rms`` is the same norm in m/s.

Results are printed as a table and written to ``OUT_DIR/compare.json``; the overlay figure
``OUT_DIR/figures/compare.png`` is laid out like Fig. 2 of the seed paper (top row φ_s, bottom row u,
one column per time, y in mm).
"""

from __future__ import annotations

import csv
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..io.atomic import write_json, write_with

EXIT_OK = 0
EXIT_INVALID = 2
#: two times match when they differ by at most this, s.
TIME_TOL = 1e-6
#: number of top bins with data averaged for the surface velocity.
SURFACE_BINS = 2
REQUIRED_COLUMNS = ("time_s", "y_m", "phi_small", "velocity_x")
RUN_VARIABLES = ("phi_small", "velocity_x")


class CompareError(ValueError):
    """Invalid input of ``compare``; the message names the file and what is wrong."""


@dataclass
class Reference:
    """Reference profiles: one row per bin and time."""

    path: Path
    time: np.ndarray
    y: np.ndarray
    phi: np.ndarray
    u: np.ndarray

    def times(self) -> np.ndarray:
        return _unique_times(self.time)

    def at(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(y, phi_small, velocity_x) of the rows at time ``t``, sorted by y."""
        m = np.abs(self.time - t) <= TIME_TOL
        order = np.argsort(self.y[m], kind="stable")
        return self.y[m][order], self.phi[m][order], self.u[m][order]


@dataclass
class RunProfiles:
    """The run's ``phi_small`` and ``velocity_x`` on (time, y)."""

    path: Path
    time: np.ndarray
    y: np.ndarray
    phi: np.ndarray
    u: np.ndarray
    #: the well-mixed small-grain fraction of the run (its initial φ_s)
    phi0: float = math.nan

    def index(self, t: float) -> int:
        return int(np.argmin(np.abs(self.time - t)))


# ---------------------------------------------------------------------------------- reading


def _unique_times(t: np.ndarray) -> np.ndarray:
    out: list[float] = []
    for v in np.sort(np.asarray(t, dtype=float)):
        if not out or v - out[-1] > TIME_TOL:
            out.append(float(v))
    return np.asarray(out)


def _parse_float(text: str, path: Path, line: int, column: str, allow_missing: bool) -> float:
    s = text.strip()
    if s == "" or s.lower() in ("nan", "na", "-nan"):
        if allow_missing:
            return math.nan
        raise CompareError(
            f"reference {str(path)!r}, line {line}: column {column!r} is empty or NaN "
            "(time_s and y_m must be finite numbers)"
        )
    try:
        v = float(s)
    except ValueError:
        raise CompareError(
            f"reference {str(path)!r}, line {line}: column {column!r} has the value {s!r}, "
            "which is not a number"
        ) from None
    if not allow_missing and not math.isfinite(v):
        raise CompareError(
            f"reference {str(path)!r}, line {line}: column {column!r} = {s!r} is not finite"
        )
    return v


def read_reference(path: str | Path) -> Reference:
    """Read a reference CSV (see the module docstring), raising :class:`CompareError`."""
    p = Path(path)
    if not p.exists():
        raise CompareError(f"reference file {str(p)!r} does not exist")
    if not p.is_file():
        raise CompareError(f"reference path {str(p)!r} is not a file")
    try:
        text = p.read_text()
    except (OSError, UnicodeDecodeError) as err:
        raise CompareError(f"reference file {str(p)!r} cannot be read: {err}") from None
    lines = [
        (i + 1, ln)
        for i, ln in enumerate(text.splitlines())
        if ln.strip() and not ln.lstrip().startswith("#")
    ]
    if not lines:
        raise CompareError(
            f"reference file {str(p)!r} has no header line; expected the columns "
            + ", ".join(REQUIRED_COLUMNS)
        )
    header_line, header = lines[0]
    try:
        names = [c.strip() for c in next(csv.reader([header]))]
    except csv.Error as err:
        raise CompareError(f"reference {str(p)!r}, line {header_line}: bad header: {err}") from None
    missing = [c for c in REQUIRED_COLUMNS if c not in names]
    if missing:
        raise CompareError(
            f"reference file {str(p)!r} lacks the column(s) {', '.join(missing)} "
            f"(header on line {header_line}: {', '.join(names) or '(empty)'}); required: "
            + ", ".join(REQUIRED_COLUMNS)
        )
    col = {c: names.index(c) for c in REQUIRED_COLUMNS}
    rows: dict[str, list[float]] = {c: [] for c in REQUIRED_COLUMNS}
    for lineno, ln in lines[1:]:
        try:
            cells = next(csv.reader([ln]))
        except csv.Error as err:
            raise CompareError(f"reference {str(p)!r}, line {lineno}: {err}") from None
        if len(cells) < len(names):
            raise CompareError(
                f"reference {str(p)!r}, line {lineno}: {len(cells)} fields, the header has "
                f"{len(names)}"
            )
        for c in REQUIRED_COLUMNS:
            rows[c].append(
                _parse_float(cells[col[c]], p, lineno, c, allow_missing=c in RUN_VARIABLES)
            )
    if not rows["time_s"]:
        raise CompareError(f"reference file {str(p)!r} has a header but no data rows")
    return Reference(
        p,
        np.asarray(rows["time_s"]),
        np.asarray(rows["y_m"]),
        np.asarray(rows["phi_small"]),
        np.asarray(rows["velocity_x"]),
    )


def read_run(out_dir: str | Path) -> RunProfiles:
    """Read ``OUT_DIR/profiles.nc`` (phi_small, velocity_x on time, y), raising :class:`CompareError`."""
    out = Path(out_dir)
    if not out.is_dir():
        raise CompareError(f"run directory {str(out)!r} does not exist")
    path = out / "profiles.nc"
    if not path.exists():
        raise CompareError(f"run profiles {str(path)!r} do not exist (is {str(out)!r} a run?)")
    import xarray as xr

    try:
        with xr.open_dataset(path, engine="h5netcdf") as ds:
            ds = ds.load()
    except Exception as err:  # any reader failure is an invalid input file
        raise CompareError(f"run profiles {str(path)!r} cannot be read: {err}") from None
    missing = [v for v in ("time", "y", *RUN_VARIABLES) if v not in ds.variables]
    if missing:
        raise CompareError(
            f"run profiles {str(path)!r} lack the variable(s) {', '.join(missing)}; required: "
            "time, y, " + ", ".join(RUN_VARIABLES)
        )
    for v in RUN_VARIABLES:
        if ds[v].dims != ("time", "y"):
            raise CompareError(
                f"run profiles {str(path)!r}: variable {v!r} has dimensions {ds[v].dims}, "
                "expected ('time', 'y')"
            )
    time = np.asarray(ds["time"].values, dtype=float)
    if time.size == 0:
        raise CompareError(f"run profiles {str(path)!r} hold no output time yet")
    phi = np.asarray(ds["phi_small"].values, dtype=float)
    return RunProfiles(
        path,
        time,
        np.asarray(ds["y"].values, dtype=float),
        phi,
        np.asarray(ds["velocity_x"].values, dtype=float),
        _well_mixed(ds, phi),
    )


def _well_mixed(ds: Any, phi: np.ndarray) -> float:
    """φ₀ of a run: ``mixture.phi_small_initial`` of the configuration in the attributes, else the
    mean of the first profile."""
    import tomllib

    try:
        cfg = tomllib.loads(str(ds.attrs.get("configuration", "")))
        return float(cfg["mixture"]["phi_small_initial"])
    except (tomllib.TOMLDecodeError, KeyError, TypeError, ValueError):
        first = phi[0][np.isfinite(phi[0])] if phi.size else np.zeros(0)
        return float(first.mean()) if first.size else math.nan


# ---------------------------------------------------------------------------------- metrics


def surface_velocity(y: np.ndarray, u: np.ndarray, nbins: int = SURFACE_BINS) -> float:
    """Mean of ``u`` over the ``nbins`` highest entries with a finite ``u`` (NaN if none)."""
    y = np.asarray(y, dtype=float)
    u = np.asarray(u, dtype=float)
    ok = np.isfinite(u) & np.isfinite(y)
    if not ok.any():
        return math.nan
    order = np.argsort(y[ok], kind="stable")
    return float(np.mean(u[ok][order][-nbins:]))


def interpolate_defined(y_run: np.ndarray, v_run: np.ndarray, y_ref: np.ndarray,
                        v_ref: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """The run interpolated at every reference height with a finite reference value (beyond
    the run's defined bins: its nearest defined value).

    Returns (y, run value, reference value, inside) at the compared points; ``inside`` marks the
    rows within the run's defined bin centres.
    """
    ok = np.isfinite(v_run) & np.isfinite(y_run)
    yr, vr = y_run[ok], v_run[ok]
    if yr.size == 0:
        empty = np.zeros(0)
        return empty, empty, empty, empty.astype(bool)
    order = np.argsort(yr)
    yr, vr = yr[order], vr[order]
    m = np.isfinite(v_ref)
    inside = (y_ref[m] >= yr[0] - 1e-12) & (y_ref[m] <= yr[-1] + 1e-12)
    return y_ref[m], np.interp(y_ref[m], yr, vr), v_ref[m], inside


def _rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(a**2))) if a.size else math.nan


def compare_time(run: RunProfiles, ref: Reference, t: float, y_offset: float) -> dict[str, Any]:
    """Error norms at one time (see the module docstring for the definitions)."""
    i = run.index(t)
    y_ref, phi_ref, u_ref = ref.at(t)
    y_ref = y_ref + y_offset
    yp, phi_run, phi_r, ip = interpolate_defined(run.y, run.phi[i], y_ref, phi_ref)
    yu, u_run, u_r, iu = interpolate_defined(run.y, run.u[i], y_ref, u_ref)
    dphi = phi_run - phi_r
    du = u_run - u_r
    us_ref = surface_velocity(y_ref, u_ref)
    us_run = surface_velocity(run.y, run.u[i])
    ok_us = math.isfinite(us_ref) and abs(us_ref) > 1e-12
    u_rms = _rms(du)
    mixed = _rms(phi_r - run.phi0) if math.isfinite(run.phi0) else math.nan
    phi_rms = _rms(dphi)
    return {
        "time": float(run.time[i]),
        "n_phi": int(dphi.size),
        "n_velocity": int(du.size),
        "n_phi_outside": int((~ip).sum()),
        "n_velocity_outside": int((~iu).sum()),
        "phi_rms": phi_rms,
        "phi_max": float(np.max(np.abs(dphi))) if dphi.size else math.nan,
        "phi_rms_mixed": mixed,
        "segregation_skill": 1.0 - phi_rms / mixed if mixed > 1e-9 else math.nan,
        "u_rms": u_rms,
        "u_rms_rel": u_rms / abs(us_ref) if ok_us else math.nan,
        "phi_rms_overlap": _rms(dphi[ip]),
        "u_rms_rel_overlap": _rms(du[iu]) / abs(us_ref) if ok_us else math.nan,
        "u_surface_run": us_run,
        "u_surface_reference": us_ref,
        "phi_small_well_mixed": run.phi0,
        "y_range_phi": [float(yp.min()), float(yp.max())] if yp.size else None,
        "y_range_velocity": [float(yu.min()), float(yu.max())] if yu.size else None,
    }


def select_times(run: RunProfiles, ref: Reference, times: list[float] | None) -> list[float]:
    """The times to compare (run's values), raising :class:`CompareError` if one is missing."""
    run_t = _unique_times(run.time)
    ref_t = ref.times()

    def has(arr: np.ndarray, t: float) -> bool:
        return bool(arr.size) and bool(np.min(np.abs(arr - t)) <= TIME_TOL)

    def listing(arr: np.ndarray) -> str:
        return ", ".join(f"{v:g}" for v in arr) or "(none)"

    if times:
        out = []
        for t in times:
            if not math.isfinite(t):
                raise CompareError(f"--times: {t!r} is not a finite time")
            if not has(run_t, t):
                raise CompareError(
                    f"--times: t = {t:g} s is not in the run's profiles {str(run.path)!r}; "
                    f"available there: {listing(run_t)} s"
                )
            if not has(ref_t, t):
                raise CompareError(
                    f"--times: t = {t:g} s is not in the reference {str(ref.path)!r}; "
                    f"available there: {listing(ref_t)} s"
                )
            out.append(float(run.time[run.index(t)]))
        return out
    common = [float(t) for t in run_t if has(ref_t, t)]
    if not common:
        raise CompareError(
            f"no time in common between the run {str(run.path)!r} ({listing(run_t)} s) and "
            f"the reference {str(ref.path)!r} ({listing(ref_t)} s)"
        )
    return common


# ---------------------------------------------------------------------------------- output


def _json_clean(v: Any) -> Any:
    if isinstance(v, float):
        return v if math.isfinite(v) else None
    if isinstance(v, dict):
        return {k: _json_clean(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_json_clean(x) for x in v]
    return v


def time_key(t: float) -> str:
    """The key of a time in ``compare.json``'s ``per_time`` (``f"{t:g}"``)."""
    return f"{t:g}"


def format_table(results: list[dict[str, Any]]) -> str:
    """The printed table."""

    def f(v: float, fmt: str) -> str:
        return format(v, fmt) if (v is not None and math.isfinite(v)) else "n/a"

    head = (
        f"{'t (s)':>8} {'n':>4} {'rms dphi':>9} {'max|dphi|':>9} {'skill':>7} {'rms du/us':>9} "
        f"{'us run':>9} {'us ref':>9}  (us: surface velocity, m/s; whole reference depth)"
    )
    rows = [head]
    for r in results:
        rows.append(
            f"{r['time']:>8g} {r['n_phi']:>4d} {f(r['phi_rms'], '9.4f')} {f(r['phi_max'], '9.4f')} "
            f"{f(r['segregation_skill'], '7.3f')} "
            f"{f(r['u_rms_rel'], '9.4f')} {f(r['u_surface_run'], '9.4g')} "
            f"{f(r['u_surface_reference'], '9.4g')}"
        )
    return "\n".join(rows)


def plot_compare(run: RunProfiles, ref: Reference, times: list[float], y_offset: float,
                 path: str | Path) -> Path:  # fmt: skip
    """The overlay figure: 2 × N panels (φ_s on top, u below), MPM lines, reference circles."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    n = len(times)
    fig, axes = plt.subplots(2, n, figsize=(3.2 * n + 0.6, 7.0), sharey=True, squeeze=False)
    ymin, ymax = 0.0, 0.0
    for j, t in enumerate(times):
        i = run.index(t)
        y_ref, phi_ref, u_ref = ref.at(t)
        y_ref_mm = (y_ref + y_offset) * 1e3
        for row, (vals_run, vals_ref, label) in enumerate(
            ((run.phi[i], phi_ref, "φ_s"), (run.u[i], u_ref, "u (m/s)"))
        ):
            ax = axes[row, j]
            ok = np.isfinite(vals_run)
            ax.plot(vals_run[ok], run.y[ok] * 1e3, "-", color="C0", lw=1.6, label="MPM")
            okr = np.isfinite(vals_ref)
            ax.plot(vals_ref[okr], y_ref_mm[okr], "o", mfc="none", mec="k", ms=4.5,
                    label="reference")  # fmt: skip
            ax.set_xlabel(label)
            ax.grid(alpha=0.3)
            for yy in (run.y[ok] * 1e3, y_ref_mm[okr]):
                if yy.size:
                    ymin, ymax = min(ymin, float(yy.min())), max(ymax, float(yy.max()))
            if row == 0:
                ax.set_title(f"t = {t:g} s")
                ax.set_xlim(0, 1)
    for row in range(2):
        axes[row, 0].set_ylabel("y (mm)")
    if ymax > ymin:
        pad = 0.03 * (ymax - ymin)
        axes[0, 0].set_ylim(ymin - pad if ymin < 0 else 0.0, ymax + pad)
    axes[0, 0].legend(fontsize=8, loc="best")
    fig.tight_layout()

    def _save(tmp: Path) -> None:
        fig.savefig(tmp, dpi=110, format="png")

    write_with(path, _save)
    plt.close(fig)
    return path


def compare(out_dir: str | Path, reference: str | Path, times: list[float] | None = None,
            y_offset: float = 0.0, figure: bool = True) -> dict[str, Any]:  # fmt: skip
    """Compare a run with a reference; returns (and writes) the ``compare.json`` content.

    Raises :class:`CompareError` on invalid input.
    """
    if not math.isfinite(y_offset):
        raise CompareError(f"--y-offset = {y_offset!r} must be a finite length in m")
    run = read_run(out_dir)
    ref = read_reference(reference)
    sel = select_times(run, ref, times)
    results = [compare_time(run, ref, t, y_offset) for t in sel]
    empty = [r["time"] for r in results if r["n_phi"] == r["n_phi_outside"]
             or r["n_velocity"] == r["n_velocity_outside"]]  # fmt: skip
    if empty:
        raise CompareError(
            f"at t = {', '.join(f'{t:g}' for t in empty)} s the run {str(run.path)!r} and the "
            f"reference {str(ref.path)!r} have no height in common (run bins "
            f"{run.y.min():.4g}–{run.y.max():.4g} m; reference y_m + y_offset with "
            f"y_offset = {y_offset:g} m): check --y-offset and the datum of y_m"
        )
    out = Path(out_dir)
    data = {
        "times": sel,
        "per_time": {time_key(r["time"]): r for r in results},
        "reference": str(Path(reference).resolve()),
        "y_offset": y_offset,
        "definitions": {
            "delta": "run - reference, run interpolated linearly at every reference y_m + "
            "y_offset with a value; beyond the run's non-empty bin centres the run's nearest "
            "value (whole depth of the reference); *_overlap: only the rows within them",
            "segregation_skill": "1 - phi_rms / phi_rms_mixed, phi_rms_mixed = rms(phi_ref - "
            "phi0), phi0 the run's initial phi_small",
            "phi_rms": "sqrt(mean(delta phi_small^2))",
            "phi_max": "max |delta phi_small|",
            "u_rms": "sqrt(mean(delta velocity_x^2)), m/s",
            "u_rms_rel": "u_rms / |u_surface_reference|",
            "u_surface": f"mean velocity_x over the {SURFACE_BINS} highest bins with data",
        },
    }
    data = _json_clean(data)
    write_json(out / "compare.json", data)
    if figure:
        data_fig = plot_compare(run, ref, sel, y_offset, out / "figures" / "compare.png")
        data["figure"] = str(data_fig)
    data["table"] = format_table(results)
    return data


def compare_run(out_dir: str | Path, reference: str | Path, times: list[float] | None = None,
                y_offset: float = 0.0) -> int:  # fmt: skip
    """CLI entry point: print the table, write compare.json and the figure; return the exit code."""
    try:
        data = compare(out_dir, reference, times, y_offset if y_offset is not None else 0.0)
    except CompareError as err:
        print(f"segmpm: error: {err}", file=sys.stderr)
        return EXIT_INVALID
    print(f"compare {out_dir} with {reference} (y_offset = {data['y_offset']:g} m)")
    print(data["table"])
    print(f"wrote {Path(out_dir) / 'compare.json'} and {data.get('figure', '')}")
    return EXIT_OK
