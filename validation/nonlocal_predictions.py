#!/usr/bin/env python
"""Predictions of DEM cases by the local and the nonlocal (grain-calibrated) models.

Every parameter comes from the DEM calibration boxes (validation/dem/calibration/calibration.json,
docs/calibration.md), none from the cases predicted here:

* ``seed``      the seed chute (26°, grain-wall friction 0.3), validation/dem/reference_profiles.csv
* ``muw015``    the same with grain-wall friction 0.15, validation/dem/cases/muw015
* ``theta27``   the same at 27°, validation/dem/cases/theta27
* ``unconfined`` the 26° inclined layer without sidewalls (calibration run incline_26, which the
  segregation fit held out), and the calibration runs ``wall030``/``wall015`` (consistency checks
  of the calibration itself, not predictions).

Models (``MODELS``): ``local_default`` (the seed's local preset ``chute_seed``, the default
before the nonlocal model replaced it), ``local_calibrated`` (local
μ(I) fitted to the inclines, measured wall law, seed Eq. 6 with driver B), ``local_lh`` (the same
with the liu_henann closure), ``nonlocal_lh``
(nonlocal granular fluidity + the liu_henann closure), ``nonlocal_htf`` (nonlocal + the Hill–Tan
flux with the fluidity's kinetic stress) and ``nonlocal_B`` (nonlocal + the seed's Eq. 6, driver B).

Each (case, model) runs as an ordinary ``segmpm run`` into validation/results/nonlocal/CASE/MODEL
(completed runs are reused), then ``segmpm compare`` against the case's DEM profiles; the table of
errors of that call goes to validation/results/nonlocal/summary.{json,md};
``validation/nonlocal_table.py`` builds the table of every completed run (table.md).

    python validation/nonlocal_predictions.py [--cases seed muw015] [--models nonlocal_lh ...]
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
CAL = HERE / "dem" / "calibration" / "calibration.json"
OUT = HERE / "results" / "nonlocal"


def calibration() -> dict:
    return json.loads(CAL.read_text())


def wall_law(cal: dict, mu_gw: float) -> dict[str, float]:
    """The measured sidewall law for a grain–wall friction μ_gw: the fits of the two dedicated
    runs (0.15, 0.3), linearly interpolated between them (valid for 0.15 ≤ μ_gw ≤ 0.3)."""
    w = cal["wall_friction"]
    lo, hi = w["wall_mu015"], w["wall_mu030"]
    s = (mu_gw - 0.15) / 0.15
    if not -1e-9 <= s <= 1 + 1e-9:
        raise ValueError(f"grain-wall friction {mu_gw} outside the calibrated 0.15-0.3")

    def lerp(k):
        return lo[k] + s * (hi[k] - lo[k])

    return {"boundary.sidewall_friction": lerp("mu_inf"),
            "boundary.sidewall_friction_slow": lerp("mu_0"),
            "boundary.sidewall_slip_speed": lerp("u_w"),
            "boundary.wall_normal_stress_ratio": lerp("K_w_mean")}  # fmt: skip


def model_overrides(cal: dict, model: str, mu_gw: float | None) -> dict[str, object]:
    """--set overrides of a model (the case's geometry comes separately)."""
    walls = wall_law(cal, mu_gw) if mu_gw is not None else {"boundary.sidewall_friction": 0.0}
    if model == "local_default":
        o = {} if mu_gw is None else {"boundary.sidewall_friction": mu_gw}
        if mu_gw is None:
            o = {"boundary.sidewall_friction": 0.0}
        return o
    lin = cal["mu_of_I"]["linear"]
    # the NGF set fitted to the incline profiles and the h_stop brackets together
    # (docs/calibration.md §3); "ngf" is h_stop alone
    ngf = {**cal["ngf_profiles"], "t0_s": cal["ngf"]["t0_s"]}
    seg = cal["segregation"]
    rc = 0.95
    local = {
        **walls,
        # q_c = q_φ 2 r_c/(1 + r_c²) = μ_s of the linear fit, a = its b
        "material.q_phi": lin["mu_s"] * (1 + rc * rc) / (2 * rc),
        "material.a": lin["b"],
    }
    c_lh = seg["lh"]["coefficients"]
    lh = {"segregation.model": "liu_henann", "segregation.lh_C_seg": c_lh["C_seg"],
          "segregation.lh_C_p": c_lh["C_p"], "segregation.lh_C_diff": c_lh["C_diff"]}  # fmt: skip
    if model == "local_calibrated":
        return local
    if model == "local_lh":
        return {**local, **lh}
    nonlocal_ = {
        **walls,
        "material.rheology": "nonlocal",
        "material.q_phi": 0.75,
        "material.static_friction": ngf["mu_s"],
        "material.rate_sensitivity": ngf["b"],
        "material.nonlocal_amplitude": ngf["A"],
        "material.fluidity_time": ngf["t0_s"],
        # the default preset's reduced stiffness (the seed preset's wave speed at q_φ = 0.75;
        # validation/stiffness_study.py --preset chute_nonlocal: within 0.2 % of 1e-3)
        "material.stiffness_scale": 5e-4,
    }
    if model == "nonlocal_lh":
        return {**nonlocal_, **lh}
    if model == "nonlocal_htf":
        c = seg["ht"]["coefficients"]
        c_D = 6.8
        kappa_g = cal["fluctuation"]["kappa_g"]
        b_c = -c_D * c["minus_b_c_over_c_D"]
        b_k = b_c + c_D * c["kappa_g_bk_minus_bc_over_c_D"] / kappa_g
        return {**nonlocal_, "segregation.model": "hill_tan_fluidity", "segregation.c_D": c_D,
                "segregation.b_k_small": b_k, "segregation.b_c_small": b_c,
                "segregation.eta": c_D * c["eta_over_c_D"],
                "segregation.kappa_g": kappa_g}  # fmt: skip
    if model == "nonlocal_B":
        return {**nonlocal_, "segregation.model": "hill_tan_reduced", "segregation.driver": "B"}
    raise KeyError(model)


MODELS = [
    "local_default",
    "local_calibrated",
    "local_lh",
    "nonlocal_lh",
    "nonlocal_htf",
    "nonlocal_B",
]

CASES = {
    "seed": dict(ref=HERE / "dem" / "reference_profiles.csv", mu_gw=0.3, over={}, end=20.0,
                 times=[1.0, 5.0, 20.0]),
    "muw015": dict(ref=HERE / "dem" / "cases" / "muw015" / "reference_profiles.csv", mu_gw=0.15,
                   over={}, end=20.0, times=[1.0, 5.0, 20.0]),
    "theta27": dict(ref=HERE / "dem" / "cases" / "theta27" / "reference_profiles.csv", mu_gw=0.3,
                    over={"geometry.slope_deg": 27.0}, end=20.0, times=[1.0, 5.0, 20.0]),
    "unconfined": dict(ref=HERE / "dem" / "calibration" / "runs" / "incline_26" / "reference_profiles.csv",
                       mu_gw=None, over={"geometry.depth": 0.025}, end=8.0,
                       times=[1.0, 2.0, 4.0, 8.0]),
    "wall030": dict(ref=HERE / "dem" / "calibration" / "runs" / "wall_mu030" / "reference_profiles.csv",
                    mu_gw=0.3, over={"geometry.depth": 0.030}, end=8.0, times=[2.0, 4.0, 8.0]),
    "wall015": dict(ref=HERE / "dem" / "calibration" / "runs" / "wall_mu015" / "reference_profiles.csv",
                    mu_gw=0.15, over={"geometry.depth": 0.030}, end=8.0, times=[2.0, 4.0, 8.0]),
}  # fmt: skip


def run_one(case: str, model: str, cal: dict) -> dict:
    c = CASES[case]
    out = OUT / case / model
    info = out / "run.json"
    if not (info.exists() and json.loads(info.read_text()).get("status") == "completed"):
        over = {**model_overrides(cal, model, c["mu_gw"]), **c["over"],
                "time.end": c["end"], "output.profile_times": sorted({0.0, *c["times"]}),
                "output.fields": False, "output.progress": False}  # fmt: skip
        # every model starts from the seed's local preset (chute_seed) and sets what differs
        args = [sys.executable, "-m", "segmpm.cli", "run", "chute_seed", "--out", str(out)]
        for k, v in over.items():
            val = json.dumps(v) if not isinstance(v, str) else f'"{v}"'
            args += ["--set", f"{k}={val}"]
        if out.exists():
            args.append("--resume")
        r = subprocess.run(args, capture_output=True, text=True)
        if r.returncode != 0:
            return {"case": case, "model": model, "error": r.stderr[-2000:]}
    r = subprocess.run([sys.executable, "-m", "segmpm.cli", "compare", str(out), str(c["ref"]),
                        "--times", *[f"{t:g}" for t in c["times"]]],
                       capture_output=True, text=True)  # fmt: skip
    if r.returncode != 0:
        return {"case": case, "model": model, "error": r.stderr[-2000:]}
    cmp = json.loads((out / "compare.json").read_text())
    run = json.loads(info.read_text())
    return {"case": case, "model": model, "wall_time_s": run["wall_time_s"],
            "per_time": {k: {q: v.get(q) for q in ("u_rms_rel", "segregation_skill", "phi_rms",
                                                    "u_surface_run", "u_surface_reference",
                                                    "u_rms_rel_overlap", "phi_rms_overlap")}
                         for k, v in cmp["per_time"].items()}}  # fmt: skip


def table(results: list[dict]) -> str:
    lines = ["| case | model | t (s) | u RMS / u_s | skill | rms Δφ | u_s run / DEM (m/s) |",
             "|---|---|---|---|---|---|---|"]  # fmt: skip
    for r in results:
        if "error" in r:
            lines.append(f"| {r['case']} | {r['model']} | error | | | | |")
            continue
        for t, v in r["per_time"].items():

            def f(x, fmt):
                return format(x, fmt) if x is not None and math.isfinite(x) else "n/a"

            lines.append(f"| {r['case']} | {r['model']} | {t} | {f(v['u_rms_rel'], '.3f')} | "
                         f"{f(v['segregation_skill'], '.2f')} | {f(v['phi_rms'], '.3f')} | "
                         f"{f(v['u_surface_run'], '.3f')} / {f(v['u_surface_reference'], '.3f')} |")  # fmt: skip
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", nargs="*", default=list(CASES))
    ap.add_argument("--models", nargs="*", default=MODELS)
    a = ap.parse_args()
    cal = calibration()
    OUT.mkdir(parents=True, exist_ok=True)
    summary_path = OUT / "summary.json"
    old = json.loads(summary_path.read_text()) if summary_path.exists() else []
    keep = {(r["case"], r["model"]): r for r in old}
    for case in a.cases:
        if not CASES[case]["ref"].exists():
            print(f"{case}: no DEM reference yet ({CASES[case]['ref']}), skipped", flush=True)
            continue
        for model in a.models:
            r = run_one(case, model, cal)
            keep[(case, model)] = r
            print(table([r]).splitlines()[-len(r.get("per_time", {1: 0})):] if "error" not in r
                  else f"{case} {model}: {r['error'][-500:]}", flush=True)  # fmt: skip
            results = sorted(keep.values(), key=lambda r: (list(CASES).index(r["case"]),
                                                            MODELS.index(r["model"])))  # fmt: skip
            summary_path.write_text(json.dumps(results, indent=1))
            (OUT / "summary.md").write_text(table(results) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
