"""Read the binned, time-averaged DEM diagnostics (``diag_z.txt`` of in.diagnostics / in.box) and
turn them into continuum fields: solid fraction, φ_s, velocity, stress (contact + kinetic),
pressure, stress ratio, shear rate, inertial number, fluidity g = γ̇/μ, fluctuation speed δv, and
(with sidewalls) the wall shear and normal stresses.

Conventions: x downslope, y across, z normal to the base (the DEM frame). ``zeta`` in the output is
the distance from the datum (the mean top of the glued layer: mean glued-centre height + r_l),
the continuum's y. Stresses are tension positive as in LAMMPS; p = −tr σ/3 and the chute stress
ratio μ = −σ_xz/σ_zz (= τ/p of the continuum's simple shear), also the invariant form
τ̄/p = √(½ s:s)/p.
"""

from __future__ import annotations

import gzip
import math
from pathlib import Path

import numpy as np

RHO_S = 2650.0
D_S, D_L = 0.002, 0.003
R_L = 0.5 * D_L


def read_chunks(path: str | Path) -> tuple[np.ndarray, list[str], np.ndarray]:
    """``fix ave/chunk`` output: (timesteps (T,), column names, data (T, n_chunks, n_cols))."""
    path = Path(path)
    opener = gzip.open if path.suffix == ".gz" else open
    steps, blocks, names = [], [], []
    with opener(path, "rt") as fh:
        lines = fh.readlines()
    i = 0
    while i < len(lines):
        ln = lines[i]
        if ln.startswith("#"):
            if ln.startswith("# Chunk"):
                names = ln[2:].split()
            i += 1
            continue
        parts = ln.split()
        step, n = int(parts[0]), int(parts[1])
        block = np.array([list(map(float, lines[i + 1 + k].split())) for k in range(n)])
        steps.append(step)
        blocks.append(block)
        i += 1 + n
    return np.array(steps), names, np.stack(blocks) if blocks else np.zeros((0, 0, 0))


def glued_datum(dump: str | Path) -> float:
    """z0 = mean z of the glued grains (type 3) + r_l, from a LAMMPS dump (gzip or not)."""
    dump = Path(dump)
    opener = gzip.open if dump.suffix == ".gz" else open
    with opener(dump, "rt") as fh:
        lines = fh.readlines()
    k = next(i for i, ln in enumerate(lines) if ln.startswith("ITEM: ATOMS"))
    cols = lines[k].split()[2:]
    data = np.loadtxt(lines[k + 1 :])
    t = data[:, cols.index("type")]
    return float(data[t == 3, cols.index("z")].mean() + R_L)


def fields(steps, names, data, *, area: float, dz: float, z0: float, dt: float = 1e-5,
           width: float | None = None, length: float | None = None) -> dict[str, np.ndarray]:  # fmt: skip
    """Continuum fields on (time, bin) from the chunk sums. ``area`` = L_x L_y (slab area),
    ``dz`` the slab thickness; ``width``/``length`` (sidewall runs): the wall spacing W and L_x
    for the wall stresses."""
    col = {n: k for k, n in enumerate(names)}

    def c(n):
        return data[:, :, col[n]]

    vol = c("v_dvol")
    with np.errstate(invalid="ignore", divide="ignore"):
        inv = np.where(vol > 0, 1.0 / vol, np.nan)
        V = area * dz
        f = vol / V
        phi = c("v_dvolS") * inv
        u = c("v_dvx") * inv
        w = c("v_dvz") * inv
        vy = c("v_dvy") * inv
        kxx = RHO_S * (c("v_dvxx") - c("v_dvx") * u) / V
        kyy = RHO_S * (c("v_dvyy") - c("v_dvy") * vy) / V
        kzz = RHO_S * (c("v_dvzz") - c("v_dvz") * w) / V
        kxz = RHO_S * (c("v_dvxz") - c("v_dvx") * w) / V
        # total stress (tension positive) = contact virial − kinetic ρ v'v'
        sxx = c("c_dsa[1]") / V - kxx
        syy = c("c_dsa[2]") / V - kyy
        szz = c("c_dsa[3]") / V - kzz
        sxy = c("c_dsa[4]") / V
        sxz = c("c_dsa[5]") / V - kxz
        syz = c("c_dsa[6]") / V
        p = -(sxx + syy + szz) / 3.0
        mu = -sxz / np.where(szz < 0, szz, np.nan)
        m = -p
        tau = np.sqrt(0.5 * ((sxx - m) ** 2 + (syy - m) ** 2 + (szz - m) ** 2)
                      + sxy**2 + sxz**2 + syz**2)  # fmt: skip
        mu_inv = tau / np.where(p > 0, p, np.nan)
        dbar = phi * D_S + (1 - phi) * D_L
        zeta = c("Coord1") - z0
        gdot = np.abs(np.gradient(u, dz, axis=1))
        inertial = gdot * dbar / np.sqrt(np.where(p > 0, p, np.nan) / RHO_S)
        g = gdot / mu_inv
        # fluctuation speed δv: the root mean square of the three velocity components' fluctuations
        dv = np.sqrt(np.where(f > 0, (kxx + kyy + kzz) / (RHO_S * np.where(f > 0, f, 1)), np.nan))
        out = dict(
            time=steps * dt, zeta=zeta[0], solid_fraction=f, phi_small=phi, u=u,
            sxx=sxx, syy=syy, szz=szz, sxz=sxz, p=p, mu=mu, mu_inv=mu_inv, gdot=gdot,
            inertial=inertial, g=g, dv=dv, dbar=dbar, kinetic_zz=kzz,
            n=c("Ncount"),
        )  # fmt: skip
        if "v_dwc" in col and width is not None and length is not None:
            # both walls: per unit wall area (2 walls × L_x × dz)
            A_w = 2.0 * length * dz
            out["wall_shear"] = -c("v_dwfx") / A_w  # the walls resist the downslope motion
            out["wall_normal"] = c("v_dwfy") / A_w
            out["wall_count"] = c("v_dwc")
            out["wall_slip"] = c("v_dwcvx") / np.where(c("v_dwc") > 0, c("v_dwc"), np.nan)
    return out


def window_mean(F: dict[str, np.ndarray], t_lo: float, t_hi: float) -> dict[str, np.ndarray]:
    """Time average of every (time, bin) field over the 0.5 s windows ending in (t_lo, t_hi]."""
    sel = (F["time"] > t_lo + 1e-9) & (F["time"] <= t_hi + 1e-9)
    out = {"zeta": F["zeta"], "n_windows": int(sel.sum())}
    for k, v in F.items():
        if isinstance(v, np.ndarray) and v.ndim == 2:
            with np.errstate(invalid="ignore"):
                out[k] = np.nanmean(v[sel], axis=0) if sel.any() else np.full(v.shape[1], np.nan)
    # the shear rate of the averaged profile (less noisy than the mean of the windows' gradients)
    dz = float(np.median(np.diff(F["zeta"])))
    out["gdot"] = np.abs(np.gradient(out["u"], dz))
    with np.errstate(invalid="ignore", divide="ignore"):
        out["inertial"] = (
            out["gdot"] * out["dbar"] / np.sqrt(np.where(out["p"] > 0, out["p"], np.nan) / RHO_S)
        )
        out["g"] = out["gdot"] / out["mu_inv"]
    return out


def surface(prof: dict[str, np.ndarray], frac: float = 0.5) -> float:
    """Height of the free surface: the top of the last bin whose solid fraction is at least
    ``frac`` of the bulk's (median over the bins below)."""
    f = prof["solid_fraction"]
    ok = np.isfinite(f) & (prof["zeta"] > 0)
    bulk = np.nanmedian(f[ok & (f > 0.3)]) if np.any(ok & (f > 0.3)) else np.nanmax(f[ok])
    idx = np.where(ok & (f >= frac * bulk))[0]
    dz = float(np.median(np.diff(prof["zeta"])))
    return float(prof["zeta"][idx.max()] + 0.5 * dz) if len(idx) else math.nan
