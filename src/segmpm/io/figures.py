"""Standard PNG figures of a run (matplotlib, non-interactive backend)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import xarray as xr  # noqa: E402

from .atomic import write_with  # noqa: E402

PANELS = (
    ("phi_small", "small-grain fraction φ_s"),
    ("velocity_x", "downslope velocity u (m/s)"),
    ("pressure", "pressure p_e (Pa)"),
    ("inertial_number", "inertial number I"),
    ("shear_rate", "shear rate γ̇ (1/s)"),
    ("segregation_driver", "segregation driver S (Pa)"),
)


def plot_profiles(ds: xr.Dataset, path: str | Path, title: str = "") -> Path:
    """Depth profiles at every output time, one panel per variable, written atomically to
    ``path`` (PNG; a failed write raises :class:`~segmpm.io.atomic.OutputWriteError` and leaves
    the previous figure and no temporary file)."""
    path = Path(path)
    names = [p for p in PANELS if p[0] in ds.data_vars]
    fig, axes = plt.subplots(2, 3, figsize=(12, 7), sharey=True)
    y_mm = ds["y"].values * 1e3
    cmap = plt.get_cmap("viridis")
    nt = ds.sizes.get("time", 0)
    for ax, (name, label) in zip(axes.flat, names, strict=False):
        for i in range(nt):
            vals = ds[name].values[i]
            ax.plot(vals, y_mm, color=cmap(i / max(1, nt - 1)),
                    label=f"t = {float(ds['time'].values[i]):g} s")  # fmt: skip
        ax.set_xlabel(label)
        ax.grid(alpha=0.3)
    for ax in axes[:, 0]:
        ax.set_ylabel("y (mm)")
    if nt:
        axes.flat[0].legend(fontsize=7)
        finite = np.isfinite(ds["phi_small"].values).any(axis=0) if "phi_small" in ds else None
        if finite is not None and finite.any():
            top = y_mm[finite].max()
            axes.flat[0].set_ylim(0, top * 1.05)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    try:
        write_with(path, lambda tmp: fig.savefig(tmp, dpi=110, format="png"))
    finally:
        plt.close(fig)
    return path
