#!/usr/bin/env python
"""Convert the LAMMPS dumps (dumps/flow_*.dump) into reference profiles.

Output
  reference_profiles.csv        profiles at t = 0, 0.5, 1, 2, 5, 10, 20 s (those available)
  reference_profiles_dense.csv  same, every 0.5 s of flow
  reference_profiles.json       datum, binning, sanity checks, overlap check, summary numbers

Columns: time_s, y_m, phi_small, velocity_x, solid_fraction, n_particles,
         solid_fraction_free, n_snapshots

Definitions
* Frame: x downslope, z normal to the base (dump coordinates); the CSV's y_m
  is the distance normal to the base measured from the datum
      z0 = mean(z of glued-grain centres) + r_large
  i.e. the mean top of the glued rough layer (value written in the JSON and
  the CSV header comment).
* Bins: slabs of thickness dz = 1 mm (= 0.5 d_s) with edges at z0 + k dz.
  Volume-weighted: each sphere's volume is split across slabs by the exact
  slab-cut sphere volume.  Glued grains are included only in
  solid_fraction (total solid volume / slab volume, slab volume =
  Lx * W * dz, W = 22 mm between the sidewalls); phi_small,
  velocity_x and solid_fraction_free use the free grains only.
  phi_small = small-grain solid volume / free solid volume in the slab;
  velocity_x = free-solid-volume-weighted mean downslope velocity.
  n_particles = mean number of free-grain centres in the slab per snapshot.
* Time averaging: profile at time T averages all dumps with |t - T| <= 0.25 s
  (dumps are every 0.25 s, i.e. 3 snapshots; 2 at the last available time).
  T = 0 is the single snapshot theta0/settled_t0.dump.gz: the same random
  mixture deposited at rest under gravity normal to the base (the
  continuum model's initial state).  The production flow run instead
  releases the random cloud under the tilted gravity at t = 0 (README).  A time T is written only when its full window is available (or T
  is the last target time and t >= T).  Bins with free solid fraction < 0.02
  are not written.
"""

import glob
import json
import math
import os
import re
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
LX, W = 0.088, 0.022
DZ = 0.001
R_L = 0.0015
PROFILE_TIMES = [0.0, 0.5, 1.0, 2.0, 5.0, 10.0, 20.0]
HALF_WIN = 0.25
MIN_FREE_FRACTION = 0.02


def read_dump(path):
    import gzip

    opener = gzip.open if path.endswith(".gz") else open
    with opener(path, "rt") as fh:
        lines = fh.readlines()
    t = None
    for i, ln in enumerate(lines):
        if ln.startswith("ITEM: TIME") and not ln.startswith("ITEM: TIMESTEP"):
            t = float(lines[i + 1])
        if ln.startswith("ITEM: ATOMS"):
            cols = ln.split()[2:]
            data = np.loadtxt(lines[i + 1 :])
            break
    d = {c: data[:, k] for k, c in enumerate(cols)}
    d["type"] = d["type"].astype(int)
    return t, d


WORK = HERE  # set by --workdir


def list_dumps():
    files = glob.glob(os.path.join(WORK, "dumps", "flow_*.dump"))
    steps = [int(re.findall(r"flow_(\d+)\.dump", f)[0]) for f in files]
    order = np.argsort(steps)
    return [files[i] for i in order], [steps[i] for i in order]


def slab_volume(zc, r, edges):
    """Volume of each sphere (centre zc, radius r) between consecutive edges.
    Returns array (n_particles, n_edges-1)."""
    h = np.clip(edges[None, :] - zc[:, None], -r[:, None], r[:, None])
    F = math.pi * (r[:, None] ** 2 * h - h**3 / 3.0)
    return np.diff(F, axis=1)


def overlaps(d):
    """Overlap / pair diameter for all contacts (grain-grain, grain-floor,
    grain-sidewall) of one snapshot.  Periodic in x via ghost copies."""
    from scipy.spatial import cKDTree

    x, y, z, r = d["x"], d["y"], d["z"], 0.5 * d["diameter"]
    n = len(x)
    idx = np.arange(n)
    lo, hi = x < 0.004, x > LX - 0.004
    gx = np.concatenate([x, x[lo] + LX, x[hi] - LX])
    gi = np.concatenate([idx, idx[lo], idx[hi]])
    gy = np.concatenate([y, y[lo], y[hi]])
    gz = np.concatenate([z, z[lo], z[hi]])
    tree = cKDTree(np.c_[gx, gy, gz])
    pairs = tree.query_pairs(0.0031, output_type="ndarray")
    a, b = gi[pairs[:, 0]], gi[pairs[:, 1]]
    keep = a < b
    a, b, p = a[keep], b[keep], pairs[keep]
    dist = np.sqrt(((tree.data[p[:, 0]] - tree.data[p[:, 1]]) ** 2).sum(1))
    delta = r[a] + r[b] - dist
    both_glued = (d["type"][a] == 3) & (d["type"][b] == 3)
    m = (delta > 0) & ~both_glued
    dpair = (r[a] + r[b])[m]  # mean diameter of the pair
    rel = delta[m] / dpair
    zpair = 0.5 * (z[a] + z[b])[m]
    # walls: floor z=0 (free grains only), sidewalls y=0 and y=W
    free = d["type"] != 3
    wall = []
    for dd in (r - z, r - y, r - (W - y)):
        mm = free & (dd > 0)
        wall.append(dd[mm] / (2 * r[mm]))
    wrel = np.concatenate(wall) if wall else np.zeros(0)
    return rel, zpair, wrel


def profile(snaps, z0, zmax):
    """Volume-weighted slab profile averaged over the snapshots."""
    kmin = -int(math.floor(z0 / DZ + 1e-9))
    kmax = int(math.ceil((zmax - z0) / DZ)) + 1
    edges = z0 + DZ * np.arange(kmin, kmax + 1)
    nb = len(edges) - 1
    vs = np.zeros(nb)
    vf = np.zeros(nb)
    vall = np.zeros(nb)
    mom = np.zeros(nb)
    cnt = np.zeros(nb)
    for d in snaps:
        r = 0.5 * d["diameter"]
        V = slab_volume(d["z"], r, edges)
        free = d["type"] != 3
        small = d["type"] == 1
        vall += V.sum(0)
        vf += V[free].sum(0)
        vs += V[small].sum(0)
        mom += (V[free] * d["vx"][free, None]).sum(0)
        k = np.floor((d["z"][free] - edges[0]) / DZ).astype(int)
        k = k[(k >= 0) & (k < nb)]
        cnt += np.bincount(k, minlength=nb)
    ns = len(snaps)
    slab = LX * W * DZ
    zc = 0.5 * (edges[:-1] + edges[1:])
    with np.errstate(invalid="ignore", divide="ignore"):
        out = dict(
            y_m=zc - z0,
            phi_small=vs / vf,
            velocity_x=mom / vf,
            solid_fraction=vall / (ns * slab),
            solid_fraction_free=vf / (ns * slab),
            n_particles=cnt / ns,
        )
    ok = out["solid_fraction_free"] >= MIN_FREE_FRACTION
    return {k: v[ok] for k, v in out.items()}


def summarise(T, p):
    """Surface velocity, static depth, top/bottom concentration of one profile."""
    sf = p["solid_fraction_free"]
    bulk = (
        np.median(sf[(p["y_m"] > 0.005) & (p["y_m"] < 0.025)])
        if np.any((p["y_m"] > 0.005) & (p["y_m"] < 0.025))
        else np.nan
    )
    above = np.where(sf >= 0.5 * bulk)[0]
    top = (
        p["y_m"][above.max()] + 0.5 * DZ if len(above) else np.nan
    )  # bed surface: last slab with f >= f_bulk/2
    surf = (p["y_m"] > top - 0.004) & (p["y_m"] <= top)
    us = float(np.average(p["velocity_x"][surf], weights=sf[surf])) if surf.any() else np.nan
    inside = (p["y_m"] > 0) & (p["y_m"] < top)
    mov = inside & (p["velocity_x"] > 0.01 * us) if us > 0 else inside & False
    y_static = float(p["y_m"][mov].min() - 0.5 * DZ) if mov.any() else np.nan
    nearbot = (p["y_m"] > 0) & (p["y_m"] < 0.005)
    neartop = (p["y_m"] > top - 0.005) & (p["y_m"] <= top)
    return dict(
        time_s=T,
        bed_surface_y_m=float(top),
        bulk_solid_fraction=float(bulk),
        surface_velocity_m_s=us,
        static_bed_top_y_m_1pct=y_static,
        velocity_at_y_5mm=float(np.interp(0.005, p["y_m"], p["velocity_x"])),
        velocity_at_y_10mm=float(np.interp(0.010, p["y_m"], p["velocity_x"])),
        phi_small_bottom_0_5mm=float(np.average(p["phi_small"][nearbot], weights=sf[nearbot]))
        if nearbot.any()
        else np.nan,
        phi_small_top_5mm=float(np.average(p["phi_small"][neartop], weights=sf[neartop]))
        if neartop.any()
        else np.nan,
    )


def write_csv(path, rows, header):
    cols = [
        "time_s",
        "y_m",
        "phi_small",
        "velocity_x",
        "solid_fraction",
        "n_particles",
        "solid_fraction_free",
        "n_snapshots",
    ]
    with open(path, "w") as fh:
        for h in header:
            fh.write("# " + h + "\n")
        fh.write(",".join(cols) + "\n")
        for T, ns, p in rows:
            for i in range(len(p["y_m"])):
                fh.write(
                    f"{T:g},{p['y_m'][i]:.5f},{p['phi_small'][i]:.5f},{p['velocity_x'][i]:.6f},"
                    f"{p['solid_fraction'][i]:.5f},{p['n_particles'][i]:.2f},"
                    f"{p['solid_fraction_free'][i]:.5f},{ns}\n"
                )


def main():
    global WORK
    import argparse

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--workdir", default=HERE, help="run directory (default: the seed reference)")
    WORK = os.path.abspath(ap.parse_args().workdir)
    files, steps = list_dumps()
    if not files:
        print("no dumps")
        return 1
    info = {}
    ipath = os.path.join(WORK, "run_info.json")
    if os.path.exists(ipath):
        info = json.load(open(ipath))
    cache = {}

    def get(i):
        if i not in cache:
            cache[i] = read_dump(files[i])
        return cache[i]

    # times from the dump headers (read lazily: use step * dt when dt known)
    dt = info.get("dt")
    if dt:
        times = np.array(steps) * dt
    else:
        times = np.array([get(i)[0] for i in range(len(files))])
    tlast = float(times.max())

    # t = 0 reference state: the bed deposited under gravity normal to the base
    # (theta0/settled_t0.dump.gz, same glued layer and same random insertion).
    # The production flow run starts from the released cloud instead (README).
    theta0 = os.path.join(HERE, "theta0", "settled_t0.dump.gz")
    if os.path.exists(theta0):
        d0 = read_dump(theta0)[1]
    else:
        d0 = get(int(np.argmin(np.abs(times))))[1]
    dflow0 = get(int(np.argmin(np.abs(times))))[1]
    g0, g1 = d0["type"] == 3, dflow0["type"] == 3
    assert np.allclose(d0["z"][g0], dflow0["z"][g1]), (
        "glued layer differs between t=0 bed and flow run"
    )
    glued = d0["type"] == 3
    zg = d0["z"][glued]
    z0 = float(zg.mean() + R_L)
    free = ~glued
    vol = math.pi / 6 * d0["diameter"] ** 3
    counts = {
        "small_free": int((d0["type"] == 1).sum()),
        "large_free": int((d0["type"] == 2).sum()),
        "large_glued": int(glued.sum()),
    }
    vfree = float(vol[free].sum())
    vsmall = float(vol[d0["type"] == 1].sum())

    def window(T):
        if T == 0.0:
            return [-1], True
        else:
            sel = np.where(np.abs(times - T) <= HALF_WIN + 1e-9)[0]
            complete = (tlast >= T + HALF_WIN - 1e-9) or (
                T == PROFILE_TIMES[-1] and tlast >= T - 1e-9
            )
        return sel, complete

    def build(targets):
        rows, summ = [], []
        for T in targets:
            sel, complete = window(T)
            if not complete or len(sel) == 0:
                continue
            snaps = [d0 if i == -1 else get(i)[1] for i in sel]
            zmax = max(float((s["z"] + 0.5 * s["diameter"]).max()) for s in snaps)
            p = profile(snaps, z0, zmax)
            rows.append((T, len(sel), p))
            summ.append(summarise(T, p))
        return rows, summ

    rows, summ = build(PROFILE_TIMES)
    dense_targets = [0.5 * k for k in range(0, int(tlast / 0.5) + 1)]
    rows_d, summ_d = build(dense_targets)

    # overlap check on the settled bed (t = 0) and on the latest profile snapshot
    ov = {}
    for label, i in (("t0_settled", -1), ("latest", int(np.argmax(times)))):
        d = d0 if i == -1 else get(i)[1]
        rel, zp, wrel = overlaps(d)
        base = zp < (
            z0 + 0.006
        )  # contacts in the bottom ~2 d_s above the datum, incl. with the glued layer

        def st(a, f):
            return float(f(a)) if len(a) else None

        ov[label] = dict(
            time_s=0.0 if i == -1 else float(times[i]),
            n_contacts=int(len(rel)),
            mean_overlap_over_d=st(rel, np.mean),
            max_overlap_over_d=st(rel, np.max),
            p99_overlap_over_d=st(rel, lambda a: np.percentile(a, 99)),
            n_contacts_over_1pct=int((rel > 0.01).sum()),
            base_mean_overlap_over_d=st(rel[base], np.mean),
            base_max_overlap_over_d=st(rel[base], np.max),
            wall_mean_overlap_over_d=st(wrel, np.mean),
            wall_max_overlap_over_d=st(wrel, np.max),
        )

    header = [
        "DEM reference (LAMMPS, see validation/dem/README.md) of the seed paper's chute case",
        f"datum: y_m = z - z0, z0 = mean glued-grain centre height + r_large = {z0:.6f} m above the base plane z=0",
        f"bins: dz = {DZ} m slabs, volume-weighted (exact slab-cut sphere volumes); phi_small and velocity_x over free grains",
        f"time averaging: dumps within +-{HALF_WIN} s of time_s (t=0: single snapshot); n_snapshots per row",
    ]
    write_csv(os.path.join(WORK, "reference_profiles.csv"), rows, header)
    write_csv(os.path.join(WORK, "reference_profiles_dense.csv"), rows_d, header)
    meta = dict(
        datum_z0_m=z0,
        datum_definition="mean z of glued-grain centres + 1.5 mm (mean top of the glued layer)",
        glued_centre_z_mean_m=float(zg.mean()),
        glued_centre_z_min_m=float(zg.min()),
        glued_centre_z_max_m=float(zg.max()),
        glued_top_max_m=float(zg.max() + R_L),
        bin_dz_m=DZ,
        binning="volume-weighted slab-cut spheres",
        half_window_s=HALF_WIN,
        counts=counts,
        free_solid_volume_m3=vfree,
        small_volume_fraction_of_free=vsmall / vfree,
        last_dump_time_s=tlast,
        n_dumps=len(files),
        run_info=info,
        summary=summ,
        summary_dense=summ_d,
        overlap_check=ov,
    )
    with open(os.path.join(WORK, "reference_profiles.json"), "w") as fh:
        json.dump(meta, fh, indent=1)
    with open(os.path.join(WORK, "results_summary.md"), "w") as fh:
        fh.write(
            "| t [s] | bed surface y [mm] | bulk f | u_surface [m/s] | u(y=10 mm) [m/s] | "
            "static below y [mm] (u < 1% u_s) | phi_s bottom 0-5 mm | phi_s top 5 mm |\n"
        )
        fh.write("|---|---|---|---|---|---|---|---|\n")
        for sm in summ_d:
            fh.write(
                f"| {sm['time_s']:g} | {sm['bed_surface_y_m'] * 1e3:.1f} | {sm['bulk_solid_fraction']:.3f} | "
                f"{sm['surface_velocity_m_s']:.3f} | {sm['velocity_at_y_10mm']:.4f} | "
                f"{sm['static_bed_top_y_m_1pct'] * 1e3:.1f} | {sm['phi_small_bottom_0_5mm']:.3f} | "
                f"{sm['phi_small_top_5mm']:.3f} |\n"
            )
    print(
        f"wrote profiles for t = {[r[0] for r in rows]} (last dump t = {tlast:g} s, datum z0 = {z0 * 1e3:.3f} mm)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
