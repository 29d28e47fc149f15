#!/usr/bin/env python
"""Plot reference_profiles.csv (phi_small, velocity_x, solid_fraction vs y) -> reference_profiles.png."""

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
df = pd.read_csv(os.path.join(HERE, "reference_profiles.csv"), comment="#")
fig, ax = plt.subplots(1, 3, figsize=(12, 5), sharey=True)
for t, g in df.groupby("time_s"):
    y = g["y_m"] * 1e3
    ax[0].plot(g["phi_small"], y, label=f"t = {t:g} s")
    ax[1].plot(g["velocity_x"], y)
    ax[2].plot(g["solid_fraction"], y)
ax[0].set_xlabel("phi_small")
ax[1].set_xlabel("velocity_x [m/s]")
ax[2].set_xlabel("solid fraction")
ax[0].set_ylabel("y above glued-layer top [mm]")
ax[0].set_xlim(0, 1)
ax[0].legend(fontsize=8)
for a in ax:
    a.axhline(0, color="k", lw=0.5)
    a.grid(alpha=0.3)
fig.suptitle("DEM (LAMMPS) chute reference: 2/3 mm spheres, 26 deg, W = 22 mm, mu_w = 0.3")
fig.tight_layout()
fig.savefig(os.path.join(HERE, "reference_profiles.png"), dpi=110)
print("wrote reference_profiles.png")
