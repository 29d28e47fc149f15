"""Local sensitivity, Gauss–Newton uncertainty and identifiability at the optimum.

Coordinates: θ_j = ln x_j for a log-scaled parameter, θ_j = x_j / s_j for a linear one with
s_j = |x*_j| (the range upper − lower if x*_j = 0): dimensionless, so a step or a standard deviation
in θ is a relative one for both kinds. J_ij = ∂r_i/∂θ_j of the per-bin residual vector r (rᵀr = the
objective) by central differences θ*_j ± step (one-sided at a bound), evaluated as one batch.

σ² = rᵀr / (m − n) at the optimum (m residuals, n parameters), C = σ² (JᵀJ)⁻¹ (over the determined
eigen-directions: a pseudo-inverse); reported: the relative standard deviations √C_jj, the standard
deviations of x (log: x* √C_jj, linear: s_j √C_jj), the correlation matrix, the eigenvalues and
eigenvectors of JᵀJ. Flags (docs/calibrate.md): a parameter whose column of J is zero has no effect
(it is set apart before the eigen-analysis); an eigen-direction with λ_max / λ > condition_limit
(default 1e8) is a combination the data cannot determine, named by the parameters with
|v_j| ≥ 0.1 in it (their standard deviation is reported as undetermined); a parameter with a
relative standard deviation above relative_std_limit (default 1) is undetermined.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .core import Evaluator, Record
from .spec import Calibration

#: an eigenvector component at least this large names a parameter of a flagged combination.
COMPONENT_MIN = 0.1


def _theta(cal: Calibration, x: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """(θ*, s) at x*: θ = ln x (log) or x / s (linear)."""
    th, s = [], []
    for p, v in zip(cal.parameters, x, strict=True):
        if p.scale == "log":
            th.append(math.log(v))
            s.append(1.0)
        else:
            sj = abs(v) if v != 0 else (p.upper - p.lower)
            th.append(v / sj)
            s.append(sj)
    return np.asarray(th), np.asarray(s)


def _x_of_theta(cal: Calibration, th: float, j: int, s: float) -> float:
    p = cal.parameters[j]
    v = math.exp(th) if p.scale == "log" else th * s
    return min(p.upper, max(p.lower, v))


def _theta_of_x(cal: Calibration, v: float, j: int, s: float) -> float:
    return math.log(v) if cal.parameters[j].scale == "log" else v / s


def sensitivity_points(cal: Calibration, best: Record) -> list[tuple[list[float], list[float]]]:
    """For each parameter, the (x₊, x₋) of its central difference (one side is x* at a bound)."""
    step = cal.spec.sensitivity.step
    th, s = _theta(cal, best.x)
    pts = []
    for j in range(len(cal.parameters)):
        xp, xm = list(best.x), list(best.x)
        xp[j] = _x_of_theta(cal, th[j] + step, j, s[j])
        xm[j] = _x_of_theta(cal, th[j] - step, j, s[j])
        pts.append((xp, xm))
    return pts


def analyse(cal: Calibration, best: Record, plus: list[Record],
            minus: list[Record]) -> dict[str, Any]:  # fmt: skip
    """The sensitivity.json content (see the module docstring)."""
    sp = cal.spec.sensitivity
    names = [p.key for p in cal.parameters]
    n = len(names)
    r0 = np.asarray(best.residuals)
    m = r0.size
    th, s = _theta(cal, best.x)
    cols, notes = [], []
    for j in range(n):
        a, b = plus[j], minus[j]
        if (
            a.status != "completed"
            or b.status != "completed"
            or len(a.residuals) != m
            or len(b.residuals) != m
        ):
            cols.append(np.full(m, np.nan))
            notes.append(f"{names[j]}: a difference point failed (evaluations {a.index:05d}, "
                         f"{b.index:05d}); its column of J is unknown")  # fmt: skip
            continue
        dth = _theta_of_x(cal, a.x[j], j, s[j]) - _theta_of_x(cal, b.x[j], j, s[j])
        if dth == 0:
            cols.append(np.full(m, np.nan))
            notes.append(f"{names[j]}: both bounds within the step; no difference possible")
            continue
        cols.append((np.asarray(a.residuals) - np.asarray(b.residuals)) / dth)
    J = np.column_stack(cols) if cols else np.zeros((m, 0))
    out: dict[str, Any] = {
        "definitions": __doc__,
        "parameters": names,
        "x_best": best.x,
        "evaluation": best.index,
        "step": sp.step,
        "condition_limit": sp.condition_limit,
        "relative_std_limit": sp.relative_std_limit,
        "n_residuals": m,
        "difference_evaluations": {
            nm: [plus[j].index, minus[j].index] for j, nm in enumerate(names)
        },  # fmt: skip
        "notes": notes,
    }
    if not np.isfinite(J).all():
        bad = [names[j] for j in range(n) if not np.isfinite(J[:, j]).all()]
        out.update(
            flags=[
                {
                    "kind": "jacobian_failed",
                    "parameters": bad,
                    "message": "the sensitivity of " + ", ".join(bad) + " could not be "
                    "computed (a difference point failed)",
                }
            ],  # fmt: skip
            unidentifiable=bad,
        )
        return out
    # parameters without any effect (a zero column) are set apart; the eigen-analysis is done on
    # the others and the no-effect ones are reported with eigenvalue 0 along their own axis
    eff = [j for j in range(n) if np.any(J[:, j] != 0)]
    noeff = [j for j in range(n) if j not in eff]
    lam_e, vec_e = (
        np.linalg.eigh(J[:, eff].T @ J[:, eff]) if eff else (np.zeros(0), np.zeros((0, 0)))
    )
    order = np.argsort(lam_e)[::-1]
    lam_e, vec_e = lam_e[order], vec_e[:, order]
    lam = [float(v) for v in lam_e] + [0.0] * len(noeff)
    vecs = []
    for k in range(len(eff)):
        v = np.zeros(n)
        v[eff] = vec_e[:, k]
        vecs.append(v)
    for j in noeff:
        v = np.zeros(n)
        v[j] = 1.0
        vecs.append(v)
    lam_max = lam[0] if eff else 0.0
    dof = m - n
    sigma2 = float(r0 @ r0) / dof if dof > 0 else math.nan
    flags, flagged = [], set()
    for j in noeff:
        flags.append({"kind": "no_effect", "parameters": [names[j]],
                      "message": f"{names[j]} has no effect on the residuals (J column zero)"})  # fmt: skip
        flagged.add(names[j])
    ratios, determined = [], []
    for k in range(len(eff)):
        ratio = lam_max / lam[k] if lam[k] > 0 else math.inf
        ratios.append(ratio)
        if ratio > sp.condition_limit:
            v = vecs[k]
            who = [names[j] for j in range(n) if abs(v[j]) >= COMPONENT_MIN]
            combo = " ".join(f"{v[j]:+.3f}·θ[{names[j]}]" for j in range(n) if abs(v[j]) >= 1e-3)
            flags.append({"kind": "combination", "parameters": who, "eigenvalue": lam[k],
                          "condition": ratio, "eigenvector": v.tolist(),
                          "message": f"the combination {combo} is not determined by the data "
                          f"(λ_max/λ = {ratio:.3g} > {sp.condition_limit:g})"})  # fmt: skip
            flagged.update(who)
        else:
            determined.append(k)
    ratios += [math.inf] * len(noeff)
    # C = σ² (JᵀJ)⁻¹ over the determined directions (a pseudo-inverse); a parameter of an
    # undetermined direction or without effect has an undetermined (infinite) deviation
    cov = np.zeros((n, n))
    for k in determined:
        cov += np.outer(vecs[k], vecs[k]) / lam[k]
    cov *= sigma2
    und = [j for j in range(n) if names[j] in flagged]
    rel_std = np.sqrt(np.abs(np.diag(cov)))
    rel_std[und] = np.inf
    with np.errstate(divide="ignore", invalid="ignore"):
        corr = cov / np.outer(rel_std, rel_std)
    corr[und, :] = np.nan
    corr[:, und] = np.nan
    cov[und, :] = np.nan
    cov[:, und] = np.nan
    x_std = [float(best.x[j] * rel_std[j]) if cal.parameters[j].scale == "log"
             else float(s[j] * rel_std[j]) for j in range(n)]  # fmt: skip
    for j in range(n):
        if names[j] not in flagged and rel_std[j] > sp.relative_std_limit:
            flags.append({"kind": "relative_std", "parameters": [names[j]],
                          "relative_std": float(rel_std[j]),
                          "message": f"{names[j]}: relative standard deviation {rel_std[j]:.3g} "
                          f"> {sp.relative_std_limit:g}"})  # fmt: skip
            flagged.add(names[j])
    out.update(
        sigma2=sigma2,
        dof=dof,
        jacobian_column_norms={nm: float(np.linalg.norm(J[:, j])) for j, nm in enumerate(names)},
        relative_std={nm: float(rel_std[j]) for j, nm in enumerate(names)},
        std={nm: x_std[j] for j, nm in enumerate(names)},
        correlation=corr.tolist(),
        covariance_theta=cov.tolist(),
        eigenvalues=lam,
        eigenvalue_ratio=ratios,
        eigenvectors=[v.tolist() for v in vecs],
        flags=flags,
        unidentifiable=[nm for nm in names if nm in flagged],
        identified=[nm for nm in names if nm not in flagged],
    )
    return out


def run_sensitivity(ev: Evaluator, best: Record) -> dict[str, Any]:
    """Evaluate the difference points of every parameter as one batch and analyse them."""
    cal = ev.cal
    pts = sensitivity_points(cal, best)
    flat = [x for pair in pts for x in pair]
    recs = ev.evaluate(flat, "sensitivity", budget=False)
    by = {tuple(r.x): r for r in recs}
    by[tuple(best.x)] = best
    plus = [by[tuple(float(v) for v in a)] for a, _ in pts]
    minus = [by[tuple(float(v) for v in b)] for _, b in pts]
    return analyse(cal, best, plus, minus)
