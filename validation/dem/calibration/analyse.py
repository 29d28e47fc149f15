#!/usr/bin/env python
"""Fit the continuum's parameters to the DEM calibration runs (run_calibration.py), none of
which is the seed case or one of its variants. Writes ``calibration.json`` (values, uncertainties,
the data behind every fit) and ``calibration.png``; docs/calibration.md explains each fit.

1. **μ(I)** from the steady inclined layers (incline_22 … 28, t ∈ (4, 8] s, bins at least 4 mm
   from the base and 3 mm below the surface): μ = −σ_xz/σ_zz against I = γ̇ d̄ / √(−σ_zz/ρ_s)
   with the local d̄. Linear law μ = μ_s + b I (the NGF's local limit) and the Jop form
   μ = μ_s + (μ_2 − μ_s)/(1 + I_0/I); standard errors from the least-squares covariance and the
   spread of one-slope-out refits.
2. **Wall friction** from wall_mu030 / wall_mu015 (flat sidewalls, grain–wall friction 0.3 and
   0.15): the mobilised ratio τ_w/σ_w of the wall stresses against the width-averaged velocity u,
   fitted by μ_w(u) = μ_0 + (μ_∞ − μ_0) u/(u + u_w) (the 2-D body force's law); the same law
   against the grains' sliding speed at the wall (``slip_law``: the resolved walls' law in 3-D);
   and K_w = σ_w/(−σ_zz).
3. **Nonlocal amplitude A** from h_stop (hstop_*): each layer of measured thickness H stopped
   between θ_stop and θ_stop + 0.5°; with the linearised NGF,
   H_stop = (π/2) A d̄ / √(tan θ − μ_s), A = 2 H √(tan θ* − μ_s)/(π d̄), θ* the bracket's middle;
   least squares over the thicknesses, the bracket as the uncertainty.
4. **F of δv = g d̄ / F** (Zhang & Kamrin 2017): δv (rms velocity fluctuation) against g d̄,
   g = γ̇/μ, in the flowing bins of the inclines: κ_g = 1/F².
5. **Segregation flux coefficients** from the time series of the small-grain profiles: the
   measured flux J(z) = −∫₀^z ∂(f φ)/∂t dz' between consecutive 0.5 s windows against the
   closures' terms (fields smoothed over 1 mm, averaged over the two windows):
   * liu_henann: J/f = d̄² (−C_seg ∂γ̇/∂z + C_p (γ̇/p) ∂p/∂z) φ(1−φ) − C_diff γ̇ d̄² ∂φ/∂z;
   * hill_tan_fluidity (Hill & Tan's full flux with σ^k = κ_g ρ (g d̄)²; only ratios to c_D are
     identifiable): J/f = [(κ_g (b^c − b^k)/c_D) ∂(g d̄)²/∂z − (b^c/c_D) g·e_z] φ(1−φ)
     − (η/c_D) ∂φ/∂z, g·e_z = −g cos θ.
   Fitted on incline_24, incline_28 and the two wall runs; incline_26 is held out (its
   prediction is in the JSON).

Usage: ``python analyse.py`` (reads runs/*, writes next to this file).
"""

from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.optimize import curve_fit

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))
import binned as B  # noqa: E402

RUNS = HERE / "runs"
D_BAR = 0.5 * (B.D_S + B.D_L)
DZ = 0.0005


def load(name: str, **kw):
    d = RUNS / name
    meta = json.loads((d / "case.json").read_text())
    case = meta["case"]
    steps, names, data = B.read_chunks(d / "diag_z.txt")
    z0 = B.glued_datum(d / "initial.dump.gz")
    walls = case["walls"] == 1
    F = B.fields(steps, names, data, area=case["Lx"] * case["Ly"], dz=DZ, z0=z0,
                 width=case["Ly"] if walls else None, length=case["Lx"] if walls else None)  # fmt: skip
    return meta, F


def steady(F, t_lo=4.0, t_hi=8.0):
    P = B.window_mean(F, t_lo, t_hi)
    with np.errstate(invalid="ignore", divide="ignore"):
        P["pzz"] = -P["szz"]
        P["I_zz"] = (
            P["gdot"] * P["dbar"] / np.sqrt(np.where(P["pzz"] > 0, P["pzz"], np.nan) / B.RHO_S)
        )
    return P, B.surface(P)


def steady_inclines():
    """(slope, steady fields, surface height) of every incline run present, in slope order."""
    for th in (22, 24, 26, 28):
        name = f"incline_{th}"
        if (RUNS / name / "case.json").exists():
            _, F = load(name)
            yield (th, *steady(F))


# ------------------------------------------------------------------------------------ μ(I)
def fit_mu_of_I(out):
    rows = []
    for th, P, H in steady_inclines():
        sel = (P["zeta"] > 0.004) & (P["zeta"] < H - 0.003) & np.isfinite(P["mu"]) & (P["I_zz"] > 0)
        for i in np.where(sel)[0]:
            rows.append((th, P["I_zz"][i], P["mu"][i], P["mu_inv"][i], P["n"][i]))
        out.setdefault("inclines", {})[f"incline_{th}"] = dict(
            surface_m=H, tan_theta=math.tan(math.radians(th)),
            mu_bulk_mean=float(np.nanmean(P["mu"][sel])),
            mu_invariant_bulk_mean=float(np.nanmean(P["mu_inv"][sel])),
            I_bulk_median=float(np.nanmedian(P["I_zz"][sel])),
            surface_velocity=float(np.nanmax(P["u"][P["zeta"] < H])),
        )  # fmt: skip
    a = np.array(rows)
    th, I, mu = a[:, 0], a[:, 1], a[:, 2]
    lin = np.polyfit(I, mu, 1, cov=True)
    (b, mu_s), cov = lin
    # one-slope-out spread
    loo = []
    for t in np.unique(th):
        k = th != t
        bb, mm = np.polyfit(I[k], mu[k], 1)
        loo.append((mm, bb))
    loo = np.array(loo)

    def jop(I, ms, m2, i0):
        return ms + (m2 - ms) / (1 + i0 / I)

    pj, cj = curve_fit(jop, I, mu, p0=(0.38, 0.64, 0.3), maxfev=20000)
    out["mu_of_I"] = dict(
        definition="mu = -sigma_xz/sigma_zz, I = gdot dbar / sqrt(-sigma_zz/rho_s), steady bins",
        n_bins=int(len(I)),
        linear=dict(mu_s=float(mu_s), b=float(b), mu_s_se=float(math.sqrt(cov[1, 1])),
                    b_se=float(math.sqrt(cov[0, 0])),
                    mu_s_leave_one_slope_out=[float(v) for v in loo[:, 0]],
                    b_leave_one_slope_out=[float(v) for v in loo[:, 1]],
                    rms_residual=float(np.sqrt(np.mean((mu - (mu_s + b * I)) ** 2)))),
        jop=dict(mu_s=float(pj[0]), mu_2=float(pj[1]), I_0=float(pj[2]),
                 se=[float(v) for v in np.sqrt(np.diag(cj))],
                 rms_residual=float(np.sqrt(np.mean((mu - jop(I, *pj)) ** 2)))),
        stress_ratio_invariant_over_chute=float(np.nanmean(a[:, 3] / a[:, 2])),
        data=dict(theta=th.tolist(), I=I.tolist(), mu=mu.tolist()),
    )  # fmt: skip
    return a


# ------------------------------------------------------------------------------ wall friction
def fit_walls(out):
    res = {}
    for name, mgw in (("wall_mu030", 0.3), ("wall_mu015", 0.15)):
        if not (RUNS / name / "case.json").exists():
            continue
        _, F = load(name)
        P, H = steady(F, 3.0, 8.0)
        sel = (P["zeta"] > 0.002) & (P["zeta"] < H - 0.001) & (P["wall_normal"] > 0)
        u = P["u"][sel]
        r = P["wall_shear"][sel] / P["wall_normal"][sel]
        K = P["wall_normal"][sel] / P["pzz"][sel]

        def law(u, m0, minf, uw):
            return m0 + (minf - m0) * u / (u + uw)

        p, c = curve_fit(law, u, r, p0=(0.05, mgw, 0.02), bounds=([0, 0, 1e-5], [1, 1, 1]))
        # the same law against the grains' own sliding speed at the wall (the mean velocity of
        # the grains touching it): the variable of a resolved wall in 3-D
        slip = P["wall_slip"][sel]
        ok = np.isfinite(slip)
        ps, cs = curve_fit(law, slip[ok], r[ok], p0=(0.05, mgw, 0.02),
                           bounds=([0, 0, 1e-5], [1, 1, 1]))  # fmt: skip
        top = P["zeta"][sel] > H - 0.004
        res[name] = dict(
            grain_wall_friction=mgw, surface_m=H,
            law="mu_w(u) = mu_0 + (mu_inf - mu_0) u/(u + u_w), u the width-averaged velocity",
            mu_0=float(p[0]), mu_inf=float(p[1]), u_w=float(p[2]),
            se=[float(v) for v in np.sqrt(np.diag(c))],
            rms_residual=float(np.sqrt(np.mean((r - law(u, *p)) ** 2))),
            slip_law=dict(
                law="mu_w(u_s) = mu_0 + (mu_inf - mu_0) u_s/(u_s + u_w), u_s the wall slip speed",
                mu_0=float(ps[0]), mu_inf=float(ps[1]), u_w=float(ps[2]),
                se=[float(v) for v in np.sqrt(np.diag(cs))],
                rms_residual=float(np.sqrt(np.mean((r[ok] - law(slip[ok], *ps)) ** 2))),
                slip_over_u_top_4mm=float(np.mean(slip[top & ok] / u[top & ok])),
            ),
            ratio_top_4mm=float(np.mean(r[top])), surface_velocity=float(np.nanmax(u)),
            K_w_mean=float(np.mean(K)), K_w_sd=float(np.std(K)),
            data=dict(zeta=P["zeta"][sel].tolist(), u=u.tolist(), ratio=r.tolist(),
                      K_w=K.tolist(), slip=P["wall_slip"][sel].tolist()),
        )  # fmt: skip
    out["wall_friction"] = res


# ---------------------------------------------------------------------------------- h_stop
def fit_hstop(out, mu_s):
    rows = []
    for d in sorted(RUNS.glob("hstop_*")):
        if not (d / "case.json").exists():
            continue
        meta, F = load(d.name)
        r = meta["result"]
        if not r or r.get("theta_stop_deg") is None:
            rows.append(dict(name=d.name, stopped=False))
            continue
        # thickness of the layer while it still flowed (the last windows before the stop)
        t_stop = r["t_stop_s"]
        P = B.window_mean(F, t_stop - 3.0, t_stop - 0.5)
        H = B.surface(P)
        th_lo, th_hi = r["theta_stop_deg"], r["theta_last_flowing_deg"]
        th_mid = 0.5 * (th_lo + th_hi)
        rows.append(dict(name=d.name, stopped=True, H=H, theta_stop=th_lo, theta_flowing=th_hi,
                         theta_mid=th_mid))  # fmt: skip
    ok = [r for r in rows if r.get("stopped") and math.tan(math.radians(r["theta_mid"])) > mu_s]
    A = [2 * r["H"] * math.sqrt(math.tan(math.radians(r["theta_mid"])) - mu_s) / (math.pi * D_BAR)
         for r in ok]  # fmt: skip
    lo = [2 * r["H"] * math.sqrt(max(math.tan(math.radians(r["theta_stop"])) - mu_s, 0)) / (math.pi * D_BAR)
          for r in ok]  # fmt: skip
    hi = [2 * r["H"] * math.sqrt(math.tan(math.radians(r["theta_flowing"])) - mu_s) / (math.pi * D_BAR)
          for r in ok]  # fmt: skip
    # least squares of H_stop(θ) = (π/2) A d̄ / √(tan θ − μ_s): H ∝ A, so A = Σ x H / Σ x²
    x = np.array([0.5 * math.pi * D_BAR / math.sqrt(math.tan(math.radians(r["theta_mid"])) - mu_s)
                  for r in ok])  # fmt: skip
    Hs = np.array([r["H"] for r in ok])
    A_ls = float(np.sum(x * Hs) / np.sum(x * x)) if len(ok) else math.nan
    # joint fit of (μ_s, A): H = (π/2) A d̄ / √(tan θ* − μ_s), θ* the bracket's middle
    joint = {}
    pts = [r for r in rows if r.get("stopped")]
    if len(pts) >= 3:
        th = np.array([math.tan(math.radians(r["theta_mid"])) for r in pts])
        Hm = np.array([r["H"] for r in pts])

        def model(t, ms, AA):
            return 0.5 * math.pi * AA * D_BAR / np.sqrt(np.maximum(t - ms, 1e-6))

        p, c = curve_fit(model, th, Hm, p0=(min(th) - 0.02, 0.5),
                         bounds=([0.0, 0.0], [min(th) - 1e-4, 10.0]))  # fmt: skip
        # the bracket (0.5°) as an error on θ: refit at both ends
        ends = []
        for key in ("theta_stop", "theta_flowing"):
            t2 = np.array([math.tan(math.radians(r[key])) for r in pts])
            pe, _ = curve_fit(model, t2, Hm, p0=p, bounds=([0.0, 0.0], [min(t2) - 1e-4, 10.0]))
            ends.append(pe)
        joint = dict(mu_s=float(p[0]), A=float(p[1]), se=[float(v) for v in np.sqrt(np.diag(c))],
                     bracket_ends=[[float(v) for v in e] for e in ends],
                     rms_residual_m=float(np.sqrt(np.mean((Hm - model(th, *p)) ** 2))))  # fmt: skip
    out["h_stop"] = dict(
        joint_fit=joint,
        runs=rows, mu_s_used=mu_s, A_per_run=A, A_bracket_lo=lo, A_bracket_hi=hi,
        A_least_squares=A_ls,
        A_se=float(np.std(A, ddof=1) / math.sqrt(len(A))) if len(A) > 1 else math.nan,
    )  # fmt: skip


def fit_ngf_b(out, a, I_max=0.3):
    """b of the NGF's local law μ = μ_s + b I with μ_s from the h_stop fit: least squares over
    the steady bins of the inclines that flow well above h_stop (24°, 26°, 28°) with I ≤ I_max (the
    range of the seed chute; the linear law does not follow the data's curvature beyond)."""
    js = out["h_stop"].get("joint_fit") or {}
    if not js:
        return
    ms = js["mu_s"]
    th, I, mu = a[:, 0], a[:, 1], a[:, 2]
    k = (th >= 24) & (I <= I_max)
    b = float(np.sum(I[k] * (mu[k] - ms)) / np.sum(I[k] ** 2))
    res = mu[k] - ms - b * I[k]
    se = float(np.sqrt(np.sum(res**2) / (k.sum() - 1) / np.sum(I[k] ** 2)))
    out["ngf"] = dict(
        mu_s=ms, mu_s_se=js["se"][0], A=js["A"], A_se=js["se"][1], b=b, b_se=se,
        b_fit_range=f"inclines 24-28 deg, I <= {I_max}", b_rms_residual=float(np.sqrt(np.mean(res**2))),
        t0_s=1.0e-3, t0_source="literature (not calibrated: steady flows do not depend on it)",
    )  # fmt: skip


def fit_ngf_profiles(out, n_nodes=800):
    """(μ_s, b, A) of the NGF fitted jointly to the steady velocity profiles of the four inclines
    (steady 1-D solve of segmpm.analysis.ngf_reference with the DEM's d̄(ζ), no sidewalls, the
    pressure floor of one grain layer) and to the h_stop brackets: residuals (u_model − u_DEM)/u_s
    at the DEM bins, and (H_stop(θ*) − H)/H of each stopped layer. scipy least_squares;
    uncertainties from the Gauss–Newton covariance J^T J at the optimum, scaled by the residual
    variance."""
    from scipy.optimize import least_squares

    from segmpm.analysis.ngf_reference import NGFParameters, steady_chute

    p_min = 0.6 * B.RHO_S * 9.81 * D_BAR  # one grain layer, as material.fluidity_floor_layers = 1
    profs = []
    for th, P, H in steady_inclines():
        sel = (P["zeta"] > 0.0) & (P["zeta"] < H) & np.isfinite(P["u"])
        y = P["zeta"][sel]
        profs.append(dict(theta=th, H=H, y=y, u=P["u"][sel], us=float(np.nanmax(P["u"][sel])),
                          dbar=(H - y, P["dbar"][sel])))  # fmt: skip
    stops = [r for r in out["h_stop"]["runs"] if r.get("stopped")]

    def residuals(x):
        ms, b, A = x
        res = []
        for pr in profs:
            prm = NGFParameters(pr["theta"], pr["H"], ms, b, A, D_BAR, p_min=p_min,
                                dbar_profile=pr["dbar"])  # fmt: skip
            try:
                r = steady_chute(prm, n_nodes)
                um = np.interp(pr["y"], r["y"][::-1], r["u"][::-1])
            except (RuntimeError, ValueError):
                um = np.zeros_like(pr["u"])
            res.append((um - pr["u"]) / pr["us"])
        for r in stops:
            ex = math.tan(math.radians(r["theta_mid"])) - ms
            hs = 0.5 * math.pi * A * D_BAR / math.sqrt(ex) if ex > 1e-6 else 10 * r["H"]
            res.append(np.array([(hs - r["H"]) / r["H"]]))
        return np.concatenate(res)

    js = out["h_stop"].get("joint_fit") or {}
    x0 = [js.get("mu_s", 0.36), out.get("ngf", {}).get("b", 0.5), js.get("A", 0.5)]
    sol = least_squares(residuals, x0, bounds=([0.30, 0.05, 0.02], [0.40, 3.0, 3.0]),
                        diff_step=1e-3)  # fmt: skip
    J = sol.jac
    dof = max(len(sol.fun) - 3, 1)
    s2 = float(np.sum(sol.fun**2) / dof)
    cov = s2 * np.linalg.pinv(J.T @ J)
    n_prof = sum(len(p["y"]) for p in profs)
    out["ngf_profiles"] = dict(
        mu_s=float(sol.x[0]), b=float(sol.x[1]), A=float(sol.x[2]),
        se=[float(v) for v in np.sqrt(np.diag(cov))],
        correlation=(cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov)))).round(3).tolist(),
        rms_velocity_residual=float(np.sqrt(np.mean(sol.fun[:n_prof] ** 2))),
        hstop_relative_residuals=[float(v) for v in sol.fun[n_prof:]],
        data="steady incline profiles (22-28 deg, t 4-8 s) and the h_stop brackets",
    )  # fmt: skip


# ------------------------------------------------------------------------------------- F of δv
def fit_F(out):
    X, Y = [], []
    for th in (24, 26, 28):
        name = f"incline_{th}"
        if not (RUNS / name / "case.json").exists():
            continue
        _, F = load(name)
        P, H = steady(F)
        sel = (P["zeta"] > 0.004) & (P["zeta"] < H - 0.003) & np.isfinite(P["g"])
        X += list(P["g"][sel] * P["dbar"][sel])
        Y += list(P["dv"][sel])
    X, Y = np.array(X), np.array(Y)
    F_ = float(np.sum(X * X) / np.sum(X * Y))  # δv = (g d̄)/F, least squares in 1/F
    out["fluctuation"] = dict(
        definition="dv = sqrt(tr <v'v'>) over the bin (three components); g = gdot/mu",
        F=F_,
        kappa_g=1.0 / F_**2,
        rms_relative_residual=float(np.sqrt(np.mean((Y - X / F_) ** 2)) / np.mean(Y)),
        n_bins=int(len(X)),
    )


# ------------------------------------------------------------------------------ segregation
def flux_samples(name, smooth=2.0):
    """(J/f, fields) between consecutive windows of one run, in the flowing part of the layer."""
    meta, F = load(name)
    theta = meta["case"]["schedule"][0][0]
    t = F["time"]
    out = []
    for k in range(1, len(t) - 1):
        if t[k] < 0.75 or t[k + 1] > 6.01:
            continue
        c1 = F["solid_fraction"][k] * F["phi_small"][k]
        c2 = F["solid_fraction"][k + 1] * F["phi_small"][k + 1]
        c1, c2 = np.nan_to_num(c1), np.nan_to_num(c2)
        dcdt = (c2 - c1) / (t[k + 1] - t[k])
        J = -np.cumsum(dcdt) * DZ  # flux through the top face of each bin (0 below the bed)
        mid = {}
        for key in ("phi_small", "u", "p", "mu_inv", "dbar", "solid_fraction", "szz"):
            a = 0.5 * (np.nan_to_num(F[key][k]) + np.nan_to_num(F[key][k + 1]))
            mid[key] = gaussian_filter1d(a, smooth)
        zeta = F["zeta"]
        f = mid["solid_fraction"]
        H = B.surface({"zeta": zeta, "solid_fraction": f})
        gdot = np.abs(np.gradient(mid["u"], DZ))
        p = -mid["szz"]
        phi = np.clip(mid["phi_small"], 0, 1)
        dbar = mid["dbar"]
        g = gdot / np.where(mid["mu_inv"] > 0.05, mid["mu_inv"], np.nan)

        # fields at the bin tops (the faces of J)
        def face(a):
            return 0.5 * (a + np.roll(a, -1))

        dphi = (np.roll(phi, -1) - phi) / DZ
        dgd = (np.roll(gdot, -1) - gdot) / DZ
        dp = (np.roll(p, -1) - p) / DZ
        S = (g * dbar) ** 2
        dS = (np.roll(S, -1) - S) / DZ
        ph, gd, pf, db, ff = face(phi), face(gdot), face(p), face(dbar), face(f)
        sel = (zeta > 0.003) & (zeta < H - 0.002) & (ff > 0.3) & (pf > 5) & np.isfinite(face(g))
        out.append(dict(
            J=J[sel] / ff[sel],
            lh=np.stack([-db[sel] ** 2 * dgd[sel] * ph[sel] * (1 - ph[sel]),
                         db[sel] ** 2 * gd[sel] / pf[sel] * dp[sel] * ph[sel] * (1 - ph[sel]),
                         -gd[sel] * db[sel] ** 2 * dphi[sel]], axis=1),
            ht=np.stack([-dS[sel] * ph[sel] * (1 - ph[sel]),
                         -9.81 * math.cos(math.radians(theta)) * ph[sel] * (1 - ph[sel]),
                         -dphi[sel]], axis=1),
        ))  # fmt: skip
    return out


def fit_segregation(out):
    train = ["incline_24", "incline_28", "wall_mu030", "wall_mu015"]
    test = ["incline_26"]
    have = [n for n in train + test if (RUNS / n / "case.json").exists()]

    def gather(names, key):
        Xs, Js = [], []
        for n in names:
            if n not in have:
                continue
            for s in flux_samples(n):
                Xs.append(s[key])
                Js.append(s["J"])
        if not Xs:
            return None, None
        X, J = np.concatenate(Xs), np.concatenate(Js)
        ok = np.all(np.isfinite(X), axis=1) & np.isfinite(J)
        return X[ok], J[ok]

    res = {}
    for key, labels in (
        ("lh", ["C_seg", "C_p", "C_diff"]),
        ("ht", ["kappa_g_bk_minus_bc_over_c_D", "minus_b_c_over_c_D", "eta_over_c_D"]),
    ):
        X, J = gather(train, key)
        if X is None:
            continue
        # non-negative least squares: every coefficient is a magnitude in its closure
        from scipy.optimize import nnls

        scale = np.sqrt(np.mean(X * X, axis=0))
        c, _ = nnls(X / scale, J)
        c = c / scale
        pred = X @ c
        # fraction of the flux explained (uncentred: the flux itself, not its variation, is the
        # quantity predicted)
        r2 = 1 - np.sum((J - pred) ** 2) / np.sum(J**2)
        # covariance of the unconstrained least squares at the optimum (Gauss-Newton)
        dof = max(len(J) - len(c), 1)
        s2 = np.sum((J - pred) ** 2) / dof
        cov = s2 * np.linalg.pinv(X.T @ X)
        Xt, Jt = gather(test, key)
        r2t = None
        if Xt is not None:
            pt = Xt @ c
            r2t = float(1 - np.sum((Jt - pt) ** 2) / np.sum(Jt**2))
        res[key] = dict(
            coefficients=dict(zip(labels, [float(v) for v in c], strict=True)),
            se=dict(zip(labels, [float(v) for v in np.sqrt(np.diag(cov))], strict=True)),
            explained_train=float(r2), explained_held_out=r2t, n_samples=int(len(J)), train=train, held_out=test,
        )  # fmt: skip
    res["note"] = ("hill_tan_fluidity with c_D fixed: b_c = -c_D * minus_b_c_over_c_D, "
                   "b_k = b_c + c_D * kappa_g_bk_minus_bc_over_c_D / kappa_g, eta = c_D * "
                   "eta_over_c_D")  # fmt: skip
    out["segregation"] = res


def main() -> int:
    out: dict = {}
    a = fit_mu_of_I(out)
    fit_walls(out)
    mu_s = out["mu_of_I"]["linear"]["mu_s"]
    fit_hstop(out, mu_s)
    fit_ngf_b(out, a)
    fit_ngf_profiles(out)
    fit_F(out)
    fit_segregation(out)
    (HERE / "calibration.json").write_text(json.dumps(out, indent=1))
    try:
        plot(out, a)
    except Exception as exc:  # noqa: BLE001
        print("plot failed:", exc)
    lin = out["mu_of_I"]["linear"]
    print(
        f"mu(I): mu_s = {lin['mu_s']:.4f} ± {lin['mu_s_se']:.4f}, b = {lin['b']:.4f} ± {lin['b_se']:.4f}"
    )
    for k, v in out["wall_friction"].items():
        print(
            f"{k}: mu_0 {v['mu_0']:.3f} mu_inf {v['mu_inf']:.3f} u_w {v['u_w']:.4f} K_w {v['K_w_mean']:.3f}"
        )
    print("h_stop joint:", out["h_stop"].get("joint_fit"))
    print("ngf:", out.get("ngf"))
    print("ngf (profiles + h_stop):", out.get("ngf_profiles"))
    print("F:", out["fluctuation"])
    print("segregation:", json.dumps(out["segregation"], indent=1))
    return 0


def plot(out, a):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(14, 4.2))
    m = out["mu_of_I"]
    I = np.array(m["data"]["I"])
    for th in np.unique(m["data"]["theta"]):
        k = np.array(m["data"]["theta"]) == th
        ax[0].plot(I[k], np.array(m["data"]["mu"])[k], ".", label=f"{th:.0f}°")
    x = np.linspace(0.005, max(I.max(), 0.5), 100)
    ax[0].plot(x, m["linear"]["mu_s"] + m["linear"]["b"] * x, "k-", label="μ_s + b I")
    j = m["jop"]
    ax[0].plot(x, j["mu_s"] + (j["mu_2"] - j["mu_s"]) / (1 + j["I_0"] / x), "k--", label="Jop")
    ax[0].set(xlabel="I", ylabel="μ = −σ_xz/σ_zz", title="steady inclines (no sidewalls)")
    ax[0].legend(fontsize=7)
    for _k, v in out["wall_friction"].items():
        u = np.array(v["data"]["u"])
        ax[1].plot(u, v["data"]["ratio"], ".", label=f"μ_gw = {v['grain_wall_friction']}")
        x = np.linspace(0, u.max(), 100)
        ax[1].plot(x, v["mu_0"] + (v["mu_inf"] - v["mu_0"]) * x / (x + v["u_w"]), "k-")
    ax[1].set(xlabel="u (m/s)", ylabel="τ_w/σ_w", title="mobilised wall friction")
    ax[1].legend(fontsize=7)
    h = out["h_stop"]
    ok = [r for r in h["runs"] if r.get("stopped")]
    ax[2].plot([r["theta_mid"] for r in ok], [1e3 * r["H"] for r in ok], "o", label="DEM")
    th = np.linspace(19, 28, 200)
    j = h["joint_fit"]
    ex = np.tan(np.radians(th)) - j["mu_s"]
    Hs = np.where(ex > 0, 0.5 * np.pi * j["A"] * D_BAR / np.sqrt(np.abs(ex)), np.nan)
    ax[2].plot(th, 1e3 * Hs, "k-", label=f"NGF fit: μ_s = {j['mu_s']:.3f}, A = {j['A']:.2f}")
    ax[2].errorbar(
        [r["theta_mid"] for r in ok], [1e3 * r["H"] for r in ok], xerr=0.25, fmt="none", ecolor="C0"
    )
    ax[2].set(xlabel="θ (°)", ylabel="H_stop (mm)", ylim=(0, 40), title="h_stop")
    ax[2].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(HERE / "calibration.png", dpi=110)


if __name__ == "__main__":
    os.chdir(HERE)
    sys.exit(main())


def export_reference(name: str, times=(0.5, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0)) -> Path:
    """The run's binned profiles as a ``compare`` reference CSV (``runs/NAME/reference_profiles.csv``):
    each time T the 0.5 s window ending at T, slabs of 0.5 mm (centre binning), y from the datum."""
    meta, F = load(name)
    path = RUNS / name / "reference_profiles.csv"
    with open(path, "w") as fh:
        fh.write(f"# DEM calibration run {name} (validation/dem/calibration), binned diag_z\n")
        fh.write(
            "# y_m from the datum (mean top of the glued layer); window: the 0.5 s ending at time_s\n"
        )
        fh.write("time_s,y_m,phi_small,velocity_x,solid_fraction,pressure,stress_ratio,fluidity\n")
        for T in times:
            k = np.where(np.abs(F["time"] - T) < 1e-6)[0]
            if not len(k):
                continue
            k = k[0]
            for i, z in enumerate(F["zeta"]):
                if not (F["solid_fraction"][k, i] > 0.05):
                    continue
                fh.write(f"{T:g},{z:.5f},{F['phi_small'][k, i]:.5f},{F['u'][k, i]:.6f},"
                         f"{F['solid_fraction'][k, i]:.4f},{F['p'][k, i]:.3f},{F['mu'][k, i]:.4f},"
                         f"{F['g'][k, i]:.4f}\n")  # fmt: skip
    return path
