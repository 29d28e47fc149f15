r"""The sidewall question (docs/validation.md §4): is the 2-D Coulomb body force an adequate reduction
of real sidewalls? Compares, on the seed chute (26°, 37.3 mm, walls 22 mm apart, μ_w = 0.3),

* the 2-D model with the body force −(2 μ_w p / W) v/|v| (run on the former plane-strain
  engine until 2026-12-07; the engine gives the same 2-D results to round-off),
* the 3-D model with two resolved Coulomb walls (generic engine, mirror plane at mid-width),
* the DEM with real flat walls (validation/dem/cases/seed: width-resolved ``diag_yz.txt``, 1 mm ×
  1 mm cells across the channel and normal to the base, and the depth profiles),

with the same local model (chute_seed, no segregation step in either continuum run). Reads the runs
written by

    segmpm run chute_seed --out validation/results/sidewall3d/body2d_h1mm <COMMON>
    segmpm run chute_seed --out validation/results/sidewall3d/walls3d_h1mm <COMMON> \
        --set geometry.dimension=3 --set geometry.mirror=true

with COMMON = --set material.rheology='"local"' --set segregation.model='"none"'
--set grid.cell_size=0.001 --set geometry.length=0.002 (see the log files beside them), and writes
validation/results/sidewall3d/summary.json and sidewall3d.png:

    python validation/sidewall3d.py [--times 0.5 1 2 5]

The same question with the default, grain-calibrated model (nonlocal fluidity, the measured wall
law μ_w(u) — on the resolved walls in 3-D, as the body force in 2-D — and the liu_henann flux):

    segmpm run --out validation/results/sidewall3d/nl_body2d_h1mm <NL>
    segmpm run --out validation/results/sidewall3d/nl_walls3d_h1mm <NL> \
        --set geometry.dimension=3 --set geometry.mirror=true
    python validation/sidewall3d.py --prefix nl_     # summary_nl.json, sidewall3d_nl.png

with NL = --set grid.cell_size=0.001 --set geometry.length=0.002 --set time.end=5
--set output.profile_times=[0.0,0.5,1.0,2.0,3.0,4.0,5.0] --set output.fields=false. Further 3-D
runs join the tables with --extra LABEL=RUN:

    segmpm run examples/chute_nonlocal_3d.toml --out validation/results/sidewall3d/nlslip_walls3d_h1mm \
        --set time.end=5 --set output.profile_times=[0.0,0.5,1.0,2.0,3.0,4.0,5.0] --set output.fields=false
    python validation/sidewall3d.py --prefix nl_ --times 0.5 1 2 3 5 \
        --extra walls_3d_slip_law=nlslip_walls3d_h1mm walls_3d_mu0.22=nlmu022_walls3d_h1mm

The 20 s runs (the example's 3-D case, 2 points per cell downslope and 3 across, and the default
2-D case at h = 1 mm; nlslip20_walls3d_h1mm is the example as it was before 2026-12-07, with 2
points per cell and axis, i.e. --set grid.particles_per_cell=2):

    segmpm run examples/chute_nonlocal_3d.toml --out validation/results/sidewall3d/nl233_20s_walls3d_h1mm \
        --set grid.threads=2 --set output.fields=false
    segmpm run --out validation/results/sidewall3d/nl_body2d20_h1mm --set grid.cell_size=0.001 \
        --set geometry.length=0.002 --set output.fields=false
    python validation/sidewall3d.py --prefix nl_ --body nl_body2d20_h1mm \
        --walls nl233_20s_walls3d_h1mm --extra two_per_cell=nlslip20_walls3d_h1mm \
        --tag nl20 --times 1 2 5 10 20   # summary_nl20.json

The flow-only controls of the late 3-D slow-down (2026-12-08; segregation off, so the grain
size stays the initial mixture's), at h = 1 mm to 10 s and at h = 11/14 mm to 6 s:

    segmpm run examples/chute_nonlocal_3d.toml --out validation/results/sidewall3d/nl233flow10_walls3d_h1mm \
        --set segregation.model='"none"' --set time.end=10 --set output.fields=false \
        --set output.profile_times=[0.0,0.5,1.0,2.0,3.0,4.0,5.0,6.0,7.0,8.0,10.0]
    segmpm run examples/chute_nonlocal_3d.toml --out validation/results/sidewall3d/nl233flow6_h0.79mm \
        --set grid.cell_size=0.0007857142857142857 --set geometry.length=0.0015714285714285715 \
        --set segregation.model='"none"' --set time.end=6 --set output.fields=false \
        --set output.profile_times=[0.0,0.5,1.0,2.0,3.0,4.0,5.0,6.0]
    python validation/sidewall3d.py --prefix nl_ --body nl_body2d20_h1mm --walls nl233_20s_walls3d_h1mm \
        --extra flow_only=nl233flow10_walls3d_h1mm --tag flow233 --times 1 2 5 10
    python validation/sidewall3d.py --prefix nl_ --body nl_body2d20_h1mm --walls nl233flow10_walls3d_h1mm \
        --extra fine_h0.79mm=nl233flow6_h0.79mm --tag flow233h --times 1 2 5

(Only the times that every run compared has in its profiles are tabled.) (The --extra labels above: the wall law fitted against the DEM's wall slip speed, and the mobilised constant μ_w = 0.22,
docs/calibration.md §2). Every 3-D run above uses the volumetric smoothing (grid.volumetric_smoothing
= "auto", on in 3-D; docs/model.md §2) unless its config.toml says otherwise; the runs
nosmooth_nlflow*_walls3d_h1mm are the flow-only (segregation.model = "none") diagnostics made
before it existed, i.e. with --set grid.volumetric_smoothing='"off"'.
"""

from __future__ import annotations

import argparse
import json
import pathlib

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import xarray as xr  # noqa: E402

HERE = pathlib.Path(__file__).parent
RES = HERE / "results" / "sidewall3d"
DEM = HERE / "dem" / "cases" / "seed"
Z0 = 0.003921800225806451  # DEM datum: mean top of the glued layer (reference_profiles.json)
W = 0.022
DT_DEM = 1e-5


def dem_windows(path: pathlib.Path = DEM / "diag_yz.txt") -> dict[float, dict[str, np.ndarray]]:
    """The width-resolved DEM windows: {end time of the 0.5 s window: arrays on (z_across, y)}.

    LAMMPS axes: y across the channel, z normal to the base; here renamed to the continuum's
    (z across, y normal, measured from the datum)."""
    out: dict[float, dict[str, np.ndarray]] = {}
    with open(path) as f:
        lines = [ln for ln in f if not ln.startswith("#")]
    i = 0
    while i < len(lines):
        step, nchunk, _ = lines[i].split()
        rows = np.array([ln.split() for ln in lines[i + 1 : i + 1 + int(nchunk)]], dtype=float)
        i += 1 + int(nchunk)
        across = np.unique(rows[:, 1])
        normal = np.unique(rows[:, 2])
        shape = (across.size, normal.size)
        vol = rows[:, 4].reshape(shape)
        out[round(int(step) * DT_DEM, 6)] = {
            "z": across, "y": normal - Z0, "vol": vol, "vol_small": rows[:, 5].reshape(shape),
            "vx_vol": rows[:, 6].reshape(shape),
        }  # fmt: skip
    return out


def dem_at(windows, t: float) -> dict[str, np.ndarray] | None:
    """The DEM fields over [t − 0.5, t + 0.5] s (the two windows around t), or None."""
    a, b = windows.get(round(t, 6)), windows.get(round(t + 0.5, 6))
    if a is None or b is None:
        return None
    vol = a["vol"] + b["vol"]
    with np.errstate(invalid="ignore", divide="ignore"):
        u = (a["vx_vol"] + b["vx_vol"]) / vol
        phi = (a["vol_small"] + b["vol_small"]) / vol
    return {"z": a["z"], "y": a["y"], "vol": vol, "u": u, "phi": phi}


def surface_speed(y: np.ndarray, u: np.ndarray, f: np.ndarray) -> tuple[float, float]:
    """(mean velocity over the top 4 mm of the dense layer, the top) of a depth profile; the top is
    the highest bin with solid fraction ≥ 0.3."""
    ok = np.isfinite(u) & np.isfinite(f) & (f >= 0.3)
    if not ok.any():
        return float("nan"), float("nan")
    top = float(y[ok].max())
    sel = ok & (y >= top - 0.004)
    return float(np.nanmean(u[sel])), top


def flowing_depth(y: np.ndarray, u: np.ndarray, top: float, us: float) -> float:
    """Depth below the top where the velocity first falls below 5 % of the surface speed."""
    ok = np.isfinite(u) & (y <= top)
    ys, uu = y[ok][::-1], u[ok][::-1]
    below = np.nonzero(uu < 0.05 * us)[0]
    return float(top - ys[below[0]]) if below.size else float(top - ys[-1])


def row_roughness(y: np.ndarray, sn: np.ndarray, top: float, band: float = 0.008) -> float:
    """Point-row noise of the normal stress over the top ``band`` of the dense layer: the RMS of
    σ_n − (its two neighbours' mean) over the mean σ_n, on the 0.5 mm bins (one bin per point row
    at h = 1 mm, 2 points per cell: a smooth profile gives ≈ 0, the row mode of docs/model.md §2
    a large value)."""
    sel = np.isfinite(sn) & (y >= top - band) & (y <= top - 0.001)
    v = sn[sel]
    if v.size < 3:
        return float("nan")
    r = v[1:-1] - 0.5 * (v[:-2] + v[2:])
    return float(np.sqrt(np.mean(r**2)) / np.mean(v[1:-1]))


def _phi_stats(y, phi, f, y_dem, phi_dem, top):
    """φ_s over the top 5 mm of the dense layer, and the skill against the DEM depth profile,
    1 − RMS(model − DEM)/RMS(0.5 − DEM), over the DEM's bins from the base to its top."""
    ok = np.isfinite(phi) & np.isfinite(f) & (f >= 0.3)
    sel = ok & (y >= top - 0.005)
    model = np.interp(y_dem, y[ok], phi[ok])
    keep = np.isfinite(phi_dem) & (y_dem >= 0)
    rms = np.sqrt(np.mean((model[keep] - phi_dem[keep]) ** 2))
    mixed = np.sqrt(np.mean((0.5 - phi_dem[keep]) ** 2))
    return float(np.mean(phi[sel])), float(rms), float(1.0 - rms / mixed)


def segregation_rows(
    ref, win, times, prefix="seg_", extra=None, body=None, walls=None
) -> list[dict]:
    """The runs with a segregation step (<prefix>body2d_h1mm or ``body``, <prefix>walls3d_h1mm
    or ``walls``, and the ``extra`` 3-D runs {label: directory}), if there."""
    runs = {
        "body_force_2d": RES / (body or f"{prefix}body2d_h1mm"),
        "walls_3d": RES / (walls or f"{prefix}walls3d_h1mm"),
        **(extra or {}),
    }
    data = {k: xr.open_dataset(d / "profiles.nc").load() for k, d in runs.items()
            if (d / "profiles.nc").exists()}  # fmt: skip
    cross3 = {k: d / "cross_section.nc" for k, d in runs.items() if k != "body_force_2d"}
    c3s = {k: xr.open_dataset(c).load() for k, c in cross3.items() if c.exists()}
    out = []
    for t in times:
        sel = np.isclose(ref["time_s"].to_numpy(), t)
        if not sel.any():
            continue
        yd, pd_ = ref["y_m"][sel].to_numpy(), ref["phi_small"][sel].to_numpy()
        fd = ref["solid_fraction"][sel].to_numpy()
        ud = ref["velocity_x"][sel].to_numpy()
        _, topd = surface_speed(yd, ud, fd)
        row: dict = {"time": t}
        seld = np.isfinite(pd_) & (yd >= topd - 0.005) & (yd <= topd)
        row["dem"] = {"phi_top5": float(np.mean(pd_[seld]))}
        for name, ds in data.items():
            if t not in ds.time.values:
                continue
            y = ds.y.values
            f = ds.solid_fraction.sel(time=t).values
            _, top = surface_speed(y, ds.velocity_x.sel(time=t).values, f)
            top5, rms, skill = _phi_stats(y, ds.phi_small.sel(time=t).values, f, yd, pd_, top)
            row[name] = {"phi_top5": top5, "phi_rms": rms, "skill": skill}
        for name, c3 in c3s.items():
            if t not in c3.time.values or name not in row:
                continue
            ys = c3.y.values
            top = float(ys[np.isfinite(c3.solid_fraction.sel(time=t).values).any(axis=1)].max())
            band = (ys >= top - 0.005) & (ys <= top)
            row[name]["phi_top5_across"] = np.nanmean(
                c3.phi_small.sel(time=t).values[band], axis=0).tolist()  # fmt: skip
        d = dem_at(win, t)
        if d is not None:
            band = (d["y"] >= topd - 0.005) & (d["y"] <= topd)
            keep = (d["z"] >= 0) & (d["z"] <= W)
            small = np.nansum((d["phi"] * d["vol"])[:, band], axis=1)
            vol = np.nansum(d["vol"][:, band], axis=1)
            with np.errstate(invalid="ignore", divide="ignore"):
                row["dem"]["phi_top5_across"] = (small / vol)[keep].tolist()
        out.append(row)
        print(json.dumps({k: ({kk: vv for kk, vv in v.items() if "across" not in kk}
                              if isinstance(v, dict) else v) for k, v in row.items()}))  # fmt: skip
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--times", type=float, nargs="+", default=[0.5, 1.0, 2.0, 5.0])
    ap.add_argument("--prefix", default="",
                    help="run-name prefix: '' the local model's flow runs (their segregation "
                         "runs are seg_*), 'nl_' the default nonlocal model's runs (segregation "
                         "on, liu_henann), written by the commands of docs/validation.md §4")  # fmt: skip
    ap.add_argument("--extra", nargs="*", default=[], metavar="LABEL=RUN",
                    help="further 3-D runs to compare, e.g. walls_3d_mu0.22=nlmu022_walls3d_h1mm "
                         "(a directory under validation/results/sidewall3d)")  # fmt: skip
    ap.add_argument("--body", default=None, help="the 2-D run (default <prefix>body2d_h1mm)")
    ap.add_argument("--walls", default=None, help="the 3-D run (default <prefix>walls3d_h1mm)")
    ap.add_argument("--tag", default=None,
                    help="names the outputs summary_<tag>.json, sidewall3d_<tag>.png "
                         "(default: the prefix)")  # fmt: skip
    args = ap.parse_args()
    pre = args.prefix
    extra = {lab: RES / run for lab, run in (e.split("=", 1) for e in args.extra)}
    body = args.body or f"{pre}body2d_h1mm"
    walls = args.walls or f"{pre}walls3d_h1mm"
    p2 = xr.open_dataset(RES / body / "profiles.nc").load()
    runs3 = {"walls_3d": RES / walls, **extra}
    p3s = {k: xr.open_dataset(d / "profiles.nc").load() for k, d in runs3.items()}
    c3s = {k: xr.open_dataset(d / "cross_section.nc").load() for k, d in runs3.items()}
    p3 = p3s["walls_3d"]
    import pandas as pd

    ref = pd.read_csv(DEM / "reference_profiles_dense.csv", comment="#")
    win = dem_windows()
    rows = []
    times = [t for t in args.times if t in p3.time.values and t in p2.time.values]
    fig, axes = plt.subplots(2, max(1, len(times)), figsize=(3.2 * max(1, len(times)), 6.4),
                             squeeze=False)  # fmt: skip
    for col, t in enumerate(times):
        row: dict = {"time": t}
        for name, ds in (("body_force_2d", p2), *p3s.items()):
            y = ds.y.values
            u = ds.velocity_x.sel(time=t).values
            f = ds.solid_fraction.sel(time=t).values
            us, top = surface_speed(y, u, f)
            sn = ds.normal_stress.sel(time=t).values
            mu = ds.stress_ratio.sel(time=t).values
            top4 = (y >= top - 0.004) & (y <= top)
            row[name] = {"surface_speed": us, "top": top,
                         "flowing_depth": flowing_depth(y, u, top, us),
                         "row_roughness_top8mm": row_roughness(y, sn, top),
                         "stress_ratio_top4mm": float(np.nanmean(mu[top4]))}  # fmt: skip
            axes[0, col].plot(u, y * 1e3, label=name.replace("_", " "))
        sel = np.isclose(ref["time_s"].to_numpy(), t)
        if sel.any():
            y, u = ref["y_m"][sel].to_numpy(), ref["velocity_x"][sel].to_numpy()
            f = ref["solid_fraction"][sel].to_numpy()
            us, top = surface_speed(y, u, f)
            row["dem"] = {"surface_speed": us, "top": top,
                          "flowing_depth": flowing_depth(y, u, top, us)}  # fmt: skip
            axes[0, col].plot(u, y * 1e3, "k--", label="DEM")
        axes[0, col].set_title(f"t = {t:g} s")
        axes[0, col].set_xlabel("u (m/s), width average")
        axes[0, 0].set_ylabel("y (mm)")
        # across the width: the velocity of the top 4 mm of the dense layer
        for name, c3 in c3s.items():
            top3 = row[name]["top"]
            ys = c3.y.values
            band = (ys >= top3 - 0.004) & (ys <= top3)
            u3z = np.nanmean(c3.velocity_x.sel(time=t).values[band], axis=0)
            z3 = c3.z.values
            row[name]["surface_u_across"] = {"z": z3.tolist(), "u": u3z.tolist()}
            # the cell nearest mid-width: the last one with the mirror plane, the middle one
            # when the whole width is modelled
            uc = u3z[int(np.argmin(np.abs(z3 - W / 2)))]
            row[name]["wall_to_centre"] = float(u3z[0] / uc) if uc else None
            axes[1, col].plot(z3 * 1e3, u3z, "o-", label=name.replace("_", " "))
        axes[1, col].axhline(row["body_force_2d"]["surface_speed"], color="C0", ls=":",
                             label="2-D body force")  # fmt: skip
        d = dem_at(win, t)
        if d is not None and "dem" in row:
            topd = row["dem"]["top"]
            bandd = (d["y"] >= topd - 0.004) & (d["y"] <= topd)
            num = np.nansum(d["u"][:, bandd] * d["vol"][:, bandd], axis=1)
            den = np.nansum(d["vol"][:, bandd], axis=1)
            with np.errstate(invalid="ignore", divide="ignore"):
                ud = num / den
            keep = (d["z"] >= 0) & (d["z"] <= W) & (den > 0)
            zz, ud = d["z"][keep], ud[keep]
            half = zz <= W / 2
            row["dem"]["surface_u_across"] = {"z": zz.tolist(), "u": ud.tolist()}
            mid = np.nanmean(ud[np.abs(zz - W / 2) <= 0.002])
            row["dem"]["wall_to_centre"] = float(np.nanmean(ud[zz <= 0.002]) / mid)
            axes[1, col].plot(zz[half] * 1e3, ud[half], "k--", label="DEM (half width)")
        axes[1, col].set_xlabel("z (mm) from the wall")
        axes[1, 0].set_ylabel("u of the top 4 mm (m/s)")
        rows.append(row)
        print(json.dumps({k: ({kk: vv for kk, vv in v.items() if kk != "surface_u_across"}
                              if isinstance(v, dict) else v) for k, v in row.items()}))  # fmt: skip
    seg = segregation_rows(ref, win, times, pre if pre else "seg_", extra,
                           args.body, args.walls)  # fmt: skip
    axes[0, 0].legend(fontsize=7)
    axes[1, 0].legend(fontsize=7)
    fig.tight_layout()
    tag = f"_{args.tag}" if args.tag else (f"_{pre.rstrip('_')}" if pre else "")
    fig.savefig(RES / f"sidewall3d{tag}.png", dpi=110)
    (RES / f"summary{tag}.json").write_text(
        json.dumps({"flow": rows, "segregation": seg}, indent=1)
    )


if __name__ == "__main__":
    main()
