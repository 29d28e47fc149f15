r"""The secondary circulation of the 3-D seed chute's cross-section (docs/validation.md §4, "Known
defect"): the point velocities v_y (normal to the base) and v_z (across the channel) of the VTK
fields, averaged over x and over 1 mm × 1 mm cells of the (y, z) cross-section, at every output
time of each run. Compares a run with the mirror plane at mid-width with one that models the whole
width, so that one can tell whether the circulation (and the deceleration it feeds) comes from the
symmetry plane.

    segmpm run examples/chute_nonlocal_3d.toml --out validation/results/sidewall3d/circ_mirror_h1mm \
        --set time.end=5 --set output.profile_times=[0.0,0.5,1.0,2.0,3.0,4.0,5.0]
    segmpm run examples/chute_nonlocal_3d.toml --out validation/results/sidewall3d/circ_full_h1mm \
        --set geometry.mirror=false --set time.end=5 \
        --set output.profile_times=[0.0,0.5,1.0,2.0,3.0,4.0,5.0]
    segmpm run examples/chute_nonlocal_3d.toml --out validation/results/sidewall3d/circ_ppc3_mirror_h1mm \
        --set grid.particles_per_cell=3 --set grid.threads=2 --set time.end=5 \
        --set output.profile_times=[0.0,0.5,1.0,2.0,3.0,4.0,5.0]
    python validation/sidewall3d_circulation.py circ_mirror_h1mm circ_ppc3_mirror_h1mm circ_full_h1mm
    segmpm run examples/chute_nonlocal_3d.toml --out validation/results/sidewall3d/circ_ppc233_mirror_h1mm \
        --set grid.particles_per_cell=[2,3,3] --set grid.threads=2 --set time.end=5 \
        --set output.profile_times=[0.0,0.5,1.0,2.0,3.0,4.0,5.0]
    python validation/sidewall3d_circulation.py circ_ppc233_mirror_h1mm --tag ppc233
    python validation/sidewall3d.py --prefix nl_ --walls circ_mirror_h1mm \
        --extra full_width=circ_full_h1mm ppc3=circ_ppc3_mirror_h1mm --tag circ --times 1 2 3 4 5

Writes validation/results/sidewall3d/circulation.json and circulation.png (circulation_TAG.* with
``--tag``). Per run and time:

* ``vy_wall``, ``vy_mid``: the mean v_y of the dense layer (cells holding at least half the
  points of a cell of the bed, the top 2 mm left out) in the cells within 2 mm of a wall and within 2 mm of mid-width;
* ``vz_max``: the largest |v_z| of a dense cell;
* ``antisymmetry`` (whole width only): max |v_z(z) + v_z(W − z)| over max |v_z|, which is 0 for a
  circulation symmetric about mid-width (what the mirror plane imposes) and of order 1 for one
  that is not.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import tomllib
import xml.etree.ElementTree as ET

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import meshio  # noqa: E402
import numpy as np  # noqa: E402

HERE = pathlib.Path(__file__).parent
RES = HERE / "results" / "sidewall3d"
CELL = 0.001  # the cross-section's bins
FILL = 0.5  # a bin is dense if it holds at least this share of the points of a bed bin


def series(run: pathlib.Path) -> list[tuple[float, pathlib.Path]]:
    """(time, .vtu path) of the run's VTK fields, from the .pvd collection."""
    pvd = next((run / "fields").glob("*.pvd"))
    root = ET.parse(pvd).getroot()
    return [
        (float(d.get("timestep")), run / "fields" / d.get("file")) for d in root.iter("DataSet")
    ]


def cross_section(path: pathlib.Path, zmax: float):
    """Bin averages over x of v_y and v_z on the (y, z) cells, and each bin's point count over
    the median count of the bins of the lower half of the layer (the filling)."""
    m = meshio.read(path)
    y, z = m.points[:, 1], m.points[:, 2]
    vy = np.ravel(m.point_data["velocity_y"])
    vz = np.ravel(m.point_data["velocity_z"])
    ny = int(np.ceil(max(y.max(), CELL) / CELL))
    nz = int(round(zmax / CELL))
    iy = np.clip((y / CELL).astype(int), 0, ny - 1)
    iz = np.clip((z / CELL).astype(int), 0, nz - 1)
    cnt = np.zeros((ny, nz))
    sy = np.zeros((ny, nz))
    sz = np.zeros((ny, nz))
    np.add.at(cnt, (iy, iz), 1.0)
    np.add.at(sy, (iy, iz), vy)
    np.add.at(sz, (iy, iz), vz)
    with np.errstate(invalid="ignore", divide="ignore"):
        uy, uz = sy / cnt, sz / cnt
    bed = cnt[: max(1, ny // 2)]
    fill = cnt / max(np.median(bed[bed > 0]), 1.0)
    return (np.arange(ny) + 0.5) * CELL, (np.arange(nz) + 0.5) * CELL, uy, uz, fill


def summarise(run: pathlib.Path) -> dict:
    geo = tomllib.loads((run / "config.toml").read_text())["geometry"]
    W = geo["width"]
    full = not geo["mirror"]
    zmax = W if full else W / 2
    rows = []
    maps = []
    for t, path in series(run):
        ys, zs, uy, uz, fill = cross_section(path, zmax)
        dense = np.isfinite(uy) & (fill >= FILL)
        top = ys[dense.any(axis=1)].max() if dense.any() else 0.0
        dense &= ys[:, None] <= top - 0.002
        zz = np.broadcast_to(zs[None, :], uy.shape)
        dwall = np.minimum(zz, zmax - zz) if full else zz
        wall = dense & (dwall <= 0.002)
        mid = dense & (np.abs(zz - W / 2) <= 0.002)
        row = {"time": t, "vy_wall": float(np.mean(uy[wall])) if wall.any() else None,
               "vy_mid": float(np.mean(uy[mid])) if mid.any() else None,
               "vz_max": float(np.max(np.abs(uz[dense]))) if dense.any() else None}  # fmt: skip
        if full and dense.any():
            anti = np.abs(uz + uz[:, ::-1])
            both = dense & dense[:, ::-1]
            row["antisymmetry"] = float(np.max(anti[both]) / max(np.max(np.abs(uz[dense])), 1e-30))
        rows.append(row)
        maps.append((t, ys, zs, np.where(dense, uy, np.nan), np.where(dense, uz, np.nan)))
    return {"full_width": full, "rows": rows, "maps": maps}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", nargs="+", help="run directories under validation/results/sidewall3d")
    ap.add_argument(
        "--tag",
        default="",
        help="write circulation_TAG.json/png (VTK fields are "
        "not committed, so a later run is summarised apart from the earlier ones)",
    )
    args = ap.parse_args()
    stem = f"circulation_{args.tag}" if args.tag else "circulation"
    out = {}
    res = {r: summarise(RES / r) for r in args.runs}
    times = sorted({row["time"] for v in res.values() for row in v["rows"] if row["time"] > 0})
    show = [t for t in times if t in (1.0, 3.0, 5.0)] or times[-3:]
    fig, axes = plt.subplots(len(res), len(show), figsize=(3.6 * len(show), 3.4 * len(res)),
                             squeeze=False)  # fmt: skip
    for r_i, (name, v) in enumerate(res.items()):
        out[name] = {"full_width": v["full_width"], "rows": v["rows"]}
        for row in v["rows"]:
            print(name, json.dumps(row))
        for c_i, t in enumerate(show):
            m = next(mm for mm in v["maps"] if mm[0] == t)
            _, ys, zs, uy, uz = m
            ax = axes[r_i, c_i]
            Z, Y = np.meshgrid(zs * 1e3, ys * 1e3)
            ax.quiver(Z, Y, uz, uy, scale=1e-4, scale_units="x")  # 10⁻⁴ m/s: 1 mm
            ax.set_title(f"{name}, t = {t:g} s\n(v_z, v_y): 1 mm per 10⁻⁴ m/s", fontsize=8)
            ax.set_xlabel("z (mm)")
            ax.set_ylabel("y (mm)")
            ax.set_aspect("equal")
    fig.tight_layout()
    fig.savefig(RES / f"{stem}.png", dpi=110)
    (RES / f"{stem}.json").write_text(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
