#!/usr/bin/env python
"""The fluidity g = γ̇/μ and ln u through the bed: DEM (binned stress and velocity of
validation/dem/cases/CASE/diag_z.txt) against the MPM runs of validation/nonlocal_predictions.py.

For each case with both: figures validation/results/nonlocal/CASE/fluidity.png (u on a log axis,
g on a log axis, μ, at the comparison times; DEM averaged over the ±1 s around each time) and the
numbers in fluidity.json (the decay length of u in the bed, fitted on ln u between 10 % and
0.1 % of the surface speed, for DEM and each model).

    python validation/fluidity_compare.py [--cases seed muw015 theta27]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE / "dem"))
import binned as B  # noqa: E402

OUT = HERE / "results" / "nonlocal"
DEM = {"seed": HERE / "dem" / "cases" / "seed", "muw015": HERE / "dem" / "cases" / "muw015",
       "theta27": HERE / "dem" / "cases" / "theta27"}  # fmt: skip
TIMES = (5.0, 20.0)
MODELS = ("local_default", "local_calibrated", "nonlocal_lh")


def dem_profiles(case: str, t: float) -> dict | None:
    d = DEM[case]
    if not (d / "diag_z.txt").exists():
        return None
    steps, names, data = B.read_chunks(d / "diag_z.txt")
    meta = json.loads((d / "reference_profiles.json").read_text())
    F = B.fields(steps, names, data, area=0.088 * 0.022, dz=0.001, z0=meta["datum_z0_m"],
                 width=0.022, length=0.088)  # fmt: skip
    if F["time"].max() < t - 1e-6:
        return None
    P = B.window_mean(F, t - 1.0, t + 1.0)
    P["H"] = B.surface(P)
    return P


def decay_length(y: np.ndarray, u: np.ndarray) -> float:
    """Slope of ln u against height where u is between 0.1 % and 10 % of its maximum, m."""
    us = np.nanmax(u)
    m = np.isfinite(u) & (u > 1e-3 * us) & (u < 0.1 * us)
    if m.sum() < 3:
        return float("nan")
    k = np.polyfit(y[m], np.log(u[m]), 1)[0]
    return float(1.0 / k) if k > 0 else float("nan")


def main() -> int:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import xarray as xr

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="*", default=list(DEM))
    a = ap.parse_args()
    for case in a.cases:
        res: dict = {}
        fig, ax = plt.subplots(len(TIMES), 3, figsize=(12, 4.2 * len(TIMES)), squeeze=False)
        for r, t in enumerate(TIMES):
            P = dem_profiles(case, t)
            row = res.setdefault(f"{t:g}", {})
            if P is not None:
                sel = (P["zeta"] > -0.002) & (P["zeta"] < P["H"])
                y = P["zeta"][sel] * 1e3
                ax[r, 0].semilogx(np.abs(P["u"][sel]), y, "ko", ms=3, label="DEM")
                ax[r, 1].semilogx(P["g"][sel], y, "ko", ms=3, label="DEM γ̇/μ")
                ax[r, 2].plot(P["mu"][sel], y, "ko", ms=3, label="DEM")
                row["DEM"] = {"decay_length_m": decay_length(P["zeta"][sel], P["u"][sel])}
            for m in MODELS:
                p = OUT / case / m / "profiles.nc"
                if not p.exists():
                    continue
                with xr.open_dataset(p, engine="h5netcdf") as ds:
                    ds = ds.load()
                k = np.where(np.abs(ds["time"].values - t) < 1e-6)[0]
                if not len(k):
                    continue
                k = k[0]
                yy = ds["y"].values
                u = ds["velocity_x"].values[k]
                ax[r, 0].semilogx(np.abs(u), yy * 1e3, "-", label=m)
                ax[r, 1].semilogx(ds["fluidity"].values[k], yy * 1e3, "-", label=m)
                ax[r, 2].plot(ds["stress_ratio"].values[k], yy * 1e3, "-", label=m)
                row[m] = {"decay_length_m": decay_length(yy, u)}
            ax[r, 0].set(xlabel="u (m/s)", ylabel="y (mm)", title=f"{case}, t = {t:g} s",
                         xlim=(1e-7, 1))  # fmt: skip
            ax[r, 1].set(xlabel="g (1/s)", xlim=(1e-4, 100))
            ax[r, 2].set(xlabel="μ", xlim=(0, 0.7))
            ax[r, 0].legend(fontsize=7)
        fig.tight_layout()
        (OUT / case).mkdir(parents=True, exist_ok=True)
        fig.savefig(OUT / case / "fluidity.png", dpi=100)
        (OUT / case / "fluidity.json").write_text(json.dumps(res, indent=1))
        print(case, json.dumps(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
