"""``segmpm calibrate`` / ``segmpm predict``: CAL.toml validation, the objective, determinism,
resume, dask (local cluster, a killed worker, a scheduler and worker started by hand), failed
evaluations, identifiability flags, parameter recovery and cross-validation.

Every calibration here fits a tiny chute (1 mm × 4 mm, 64 points, 0.05 s: about half a second
per run once compiled) against a synthetic reference made by the model itself with known values.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from conftest import SUBPROCESS_ENV

from segmpm import calibrate as cal_mod
from segmpm.analysis.compare import compare
from segmpm.cli import main
from segmpm.config import ScenarioConfig, load_config
from segmpm.simulation import Simulation

HAS_COLUMN = "solver" in ScenarioConfig.model_fields
TRUE_MU_W = 0.3
BASE = """extends = "chute_seed"
[geometry]
depth = 0.004
length = 0.001
"""
TIMES = [0.025, 0.05]


def write_reference(run_dir: Path, csv: Path) -> None:
    """A reference CSV (compare's format) from a run's profiles.nc."""
    with xr.open_dataset(run_dir / "profiles.nc", engine="h5netcdf") as ds:
        lines = ["time_s,y_m,phi_small,velocity_x"]
        for i, t in enumerate(ds["time"].values):
            for y, p, u in zip(ds["y"].values, ds["phi_small"].values[i],
                               ds["velocity_x"].values[i], strict=True):  # fmt: skip
                if np.isfinite(p) and np.isfinite(u):
                    lines.append(f"{float(t)!r},{float(y)!r},{float(p)!r},{float(u)!r}")
    csv.write_text("\n".join(lines) + "\n")


def synthetic_reference(folder: Path, overrides: list[str], name: str,
                        end: float = 0.05) -> Path:  # fmt: skip
    """Run the base with ``overrides`` (the "true" values) and write its profiles as a CSV."""
    times = sorted({0.0, *TIMES, end})
    cfg = load_config(folder / "base.toml", overrides + [
        f"time.end={end}", f"output.profile_times={times}", "output.fields=false",
        "output.figures=false", "output.progress=false"])  # fmt: skip
    run = folder / f"run-{name}"
    Simulation(cfg, out_dir=run).run(progress=False)
    csv = folder / f"{name}.csv"
    write_reference(run, csv)
    return csv


@pytest.fixture(scope="module")
def refs(tmp_path_factory) -> Path:
    d = tmp_path_factory.mktemp("refs")
    (d / "base.toml").write_text(BASE)
    synthetic_reference(d, [f"boundary.sidewall_friction={TRUE_MU_W}"], "ref")
    synthetic_reference(d, ["boundary.sidewall_friction=0.3", "geometry.slope_deg=28.0"],
                        "heldout")  # fmt: skip
    return d


CAL_1P = """
[[parameters]]
key = "boundary.sidewall_friction"
lower = 0.1
upper = 0.6

[[cases]]
name = "tiny"
reference = "{ref}"
base = "{base}"
times = [0.025, 0.05]

[optimiser]
method = "lhs_then_local"
samples = 4
max_evaluations = 10
"""


def write_cal(folder: Path, refs: Path, text: str = CAL_1P, name: str = "cal.toml") -> Path:
    p = folder / name
    p.write_text(text.format(ref=refs / "ref.csv", base=refs / "base.toml",
                             heldout=refs / "heldout.csv"))  # fmt: skip
    return p


def history(out: Path) -> xr.Dataset:
    with xr.open_dataset(out / "history.nc", engine="h5netcdf") as ds:
        return ds.load()


@pytest.fixture(scope="module")
def reference_run(refs, tmp_path_factory) -> Path:
    """One uninterrupted calibration on a LocalCluster of 2 worker processes (the default)."""
    d = tmp_path_factory.mktemp("cal-a")
    cal = write_cal(d, refs)
    assert cal_mod.run_calibration(cal, d / "out", workers=2) == 0
    return d / "out"


# ---------------------------------------------------------------------------------- validation


@pytest.mark.parametrize(
    "edit, needles",
    [
        (("lower = 0.1", "lower = 0.7"), ["lower = 0.7", "upper = 0.6", "smaller"]),
        (
            ("boundary.sidewall_friction", "boundary.sidewal_friction"),
            ["sidewal_friction", "sidewall_friction_slow"],
        ),  # fmt: skip
        (("lower = 0.1", 'lower = 0.0\nscale = "log"'), ["scale = 'log'", "lower > 0"]),
        (("upper = 0.6", "upper = 20.0"), ["boundary.sidewall_friction = 20.0", "≤ 10"]),
        (
            ('method = "lhs_then_local"', 'method = "nelder"'),
            ["optimiser.method", "'nelder'", "'differential_evolution'"],
        ),  # fmt: skip
        (("samples = 4", "popsize = 0"), ["optimiser.popsize = 0", "≥ 1"]),
        (("[optimiser]", "[optimizer]"), ["'optimizer'", "optimiser"]),
        (
            ("max_evaluations = 10", "max_evaluations = 10\ntolerance = -1.0"),
            ["optimiser.tolerance = -1.0", "> 0"],
        ),  # fmt: skip
        (("times = [0.025, 0.05]", "times = [0.025, 0.03]"), ["t = 0.03", "0.025"]),
        (
            ("times = [0.025, 0.05]", "times = [0.025, 0.05]\ntime_weights = [1.0]"),
            ["time_weights", "1 entries", "2"],
        ),  # fmt: skip
        (('name = "tiny"', 'name = "a b"'), ["cases[0]", "name = 'a b'"]),
        (("samples = 4", 'samples = 4\n[inner]\nmodel = "fem"'), ["inner.model", "'column'"]),
    ],
)
def test_invalid_cal_exits_2_naming_the_key(tmp_path, refs, capsys, edit, needles):
    text = CAL_1P.replace(*edit)
    assert text != CAL_1P
    cal = write_cal(tmp_path, refs, text)
    out = tmp_path / "out"
    assert main(["calibrate", str(cal), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    for n in needles:
        assert n in err, err
    assert "Traceback" not in err
    assert not (out / "evals").exists()  # nothing ran


def test_invalid_cal_files_exit_2(tmp_path, refs, capsys):
    assert main(["calibrate", str(tmp_path / "none.toml")]) == 2
    assert "none.toml" in capsys.readouterr().err
    cal = write_cal(tmp_path, refs, CAL_1P.replace("{base}", "no_such_preset"))
    assert main(["calibrate", str(cal), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "no_such_preset" in err and "chute_seed" in err
    cal = write_cal(tmp_path, refs, CAL_1P.replace("{ref}", "missing.csv"))
    assert main(["calibrate", str(cal), "--out", str(tmp_path / "o")]) == 2
    assert "missing.csv" in capsys.readouterr().err
    cal = write_cal(tmp_path, refs, CAL_1P.replace("[[cases]]", "[[cases]]\nset = ['time.cfl=7']"))
    assert main(["calibrate", str(cal), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "time.cfl = 7" in err and "≤ 1" in err
    if not HAS_COLUMN:
        cal = write_cal(tmp_path, refs, CAL_1P + '[inner]\nmodel = "column"\n')
        assert main(["calibrate", str(cal), "--out", str(tmp_path / "o")]) == 2
        assert "scenario.solver" in capsys.readouterr().err


def test_inner_model_sets_scenario_solver_only_for_the_column(tmp_path, refs):
    cal = cal_mod.load_calibration(write_cal(tmp_path, refs))
    case = cal.cases[0]
    data = case.config_data({"boundary.sidewall_friction": 0.25}, "mpm")
    assert "solver" not in data.get("scenario", {})
    assert data["boundary"]["sidewall_friction"] == 0.25
    assert data["time"]["end"] == 0.05 and data["output"]["profile_times"] == [0.0, 0.025, 0.05]
    assert case.config_data({}, "column")["scenario"]["solver"] == "column"


# ---------------------------------------------------------------------------------- runs


def test_recovers_the_parameter_and_objective_is_the_compare_metric(reference_run, refs):
    best = json.loads((reference_run / "best.json").read_text())
    mu = best["parameters"]["boundary.sidewall_friction"]
    assert abs(mu - TRUE_MU_W) < 0.05 * TRUE_MU_W
    h = history(reference_run)
    assert list(h["evaluation"].values) == list(range(h.sizes["evaluation"]))
    assert best["objective"] == float(h["objective"].where(h["stage"] != "sensitivity").min())
    assert float(h["best_so_far"][-1]) == best["objective"]
    # the objective is compare's norms: J = mean over the times of phi_rms² + u_rms_rel²
    worst = int(np.argmax(h["objective"].values))
    run_dir = reference_run / "evals" / f"{worst:05d}" / "tiny"
    cmp = compare(run_dir, refs / "ref.csv", TIMES, figure=False)
    terms = [cmp["per_time"][f"{t:g}"] for t in TIMES]
    expected = np.mean([r["phi_rms"] ** 2 + r["u_rms_rel"] ** 2 for r in terms])
    assert float(h["objective"][worst]) == pytest.approx(expected, rel=1e-12)
    ev = json.loads((reference_run / "evals" / f"{worst:05d}" / "eval.json").read_text())
    assert sum(v * v for v in ev["residuals"]) == pytest.approx(expected, rel=1e-10)
    np.testing.assert_allclose(h["phi_rms"][worst], [r["phi_rms"] for r in terms], rtol=1e-12)
    # a far point is much worse than the best, and best.toml is a runnable configuration
    assert float(h["objective"][worst]) > 100 * best["objective"]
    cfg = load_config(reference_run / "best.toml")
    assert cfg.boundary.sidewall_friction == mu
    for f in ("objective.png", "profiles.png", "sensitivity.json", "best-tiny.toml"):
        assert (reference_run / f).stat().st_size > 0
    sens = json.loads((reference_run / "sensitivity.json").read_text())
    assert sens["identified"] == ["boundary.sidewall_friction"] and not sens["flags"]


def _same_history(a: xr.Dataset, b: xr.Dataset) -> None:
    assert a.sizes["evaluation"] == b.sizes["evaluation"]
    for v in ("x", "objective", "phi_rms", "u_rms_rel"):
        np.testing.assert_array_equal(a[v].values, b[v].values)
    assert list(a["status"].values) == list(b["status"].values)
    assert list(a["stage"].values) == list(b["stage"].values)


def test_deterministic_and_resumes_without_repeating_or_losing(reference_run, refs, tmp_path,
                                                               capsys):  # fmt: skip
    cal = write_cal(tmp_path, refs)
    out = tmp_path / "out"
    # "interrupted" after 5 new evaluations, in the middle of the first local batches
    assert cal_mod.run_calibration(cal, out, workers=2, stop_after=5) == 130
    assert "re-run the same command" in capsys.readouterr().err
    done = sorted(out.glob("evals/*/eval.json"))
    assert len(done) >= 5
    stamps = {p: p.stat().st_mtime_ns for p in out.glob("evals/*/*/result.json")}
    assert cal_mod.run_calibration(cal, out, workers=2) == 0
    err = capsys.readouterr().err
    assert f"{len(done)} evaluation(s) already in" in err
    for p, ns in stamps.items():  # a completed evaluation is never run again
        assert p.stat().st_mtime_ns == ns, p
    h = history(out)
    xs = [tuple(row) for row in h["x"].values]
    assert len(set(xs)) == len(xs)  # no vector evaluated twice
    _same_history(h, history(reference_run))  # same file → same history, interrupted or not
    # a third run finds everything on disk: nothing is run, no cluster started
    assert cal_mod.run_calibration(cal, out, workers=2) == 0
    err = capsys.readouterr().err
    assert "0 new" in err and "local worker" not in err
    # a changed CAL is refused in the same OUT (the budget keys may change)
    cal.write_text(cal.read_text().replace("upper = 0.6", "upper = 0.5"))
    assert main(["calibrate", str(cal), "--out", str(out)]) == 2
    assert "parameters[0].upper" in capsys.readouterr().err


def test_worker_killed_mid_calibration_loses_no_evaluation(reference_run, refs, tmp_path):
    """A worker process is SIGKILLed while the first batch runs; dask reruns its task on the
    other (or the restarted) worker; completed evaluations stay on disk and are not rerun."""
    import logging

    from distributed import Client, LocalCluster

    cal = write_cal(tmp_path, refs)
    out = tmp_path / "out"
    killed: dict[str, object] = {}

    def on_batch(client, futures):
        if killed or len(futures) < 2:
            return

        def kill():
            deadline = time.time() + 60
            while time.time() < deadline and not any(f.done() for f in futures):
                time.sleep(0.02)
            stamps = {p: p.stat().st_mtime_ns for p in out.glob("evals/*/*/result.json")}
            busy = [w for w, keys in client.processing().items() if keys]
            if busy:  # the worker running a task of this batch
                pids = client.run(os.getpid)
                os.kill(pids[busy[0]], signal.SIGKILL)
                killed.update(worker=busy[0], stamps=stamps)

        threading.Thread(target=kill, daemon=True).start()

    env = {"NUMBA_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    with LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=logging.CRITICAL, env=env) as cluster:  # fmt: skip
        with Client(cluster):
            code = cal_mod.run_calibration(cal, out, scheduler=cluster.scheduler_address,
                                           on_batch=on_batch)  # fmt: skip
    assert code == 0
    assert killed.get("worker"), "no worker was killed"
    for p, ns in killed["stamps"].items():
        assert p.stat().st_mtime_ns == ns, p
    _same_history(history(out), history(reference_run))


def test_failed_evaluation_is_recorded_and_penalised(tmp_path, refs):
    # dt_min = 2e-5 s: a Courant number below about 0.4 collapses the time step (exit 3)
    text = """
[[parameters]]
key = "time.cfl"
lower = 0.1
upper = 0.9

[[cases]]
reference = "{ref}"
base = "{base}"
set = ["time.dt_min=2e-5"]
times = [0.05]

[optimiser]
samples = 4
max_evaluations = 4

[sensitivity]
enabled = false
"""
    cal = write_cal(tmp_path, refs, text)
    out = tmp_path / "out"
    assert cal_mod.run_calibration(cal, out, workers=2) == 0
    h = history(out)
    status = list(h["status"].values)
    cfl = h["x"].values[:, 0]
    assert "failed" in status and "completed" in status
    for i, s in enumerate(status):
        if s == "failed":
            assert float(h["objective"][i]) == cal_mod.PENALTY
            assert cfl[i] < 0.45
            assert "time step" in str(h["message"].values[i]).lower()
            rec = json.loads((out / "evals" / f"{i:05d}" / "eval.json").read_text())
            assert rec["status"] == "failed"
        else:
            assert float(h["objective"][i]) < 1.0
    best = json.loads((out / "best.json").read_text())
    assert best["summary"]["failed"] == status.count("failed")
    assert best["parameters"]["time.cfl"] >= 0.45


def test_sensitivity_flags_unidentifiable_parameters(tmp_path, refs):
    """κ and κ_T enter the seed's driver B only as the product κ κ_T ρ (γ̇ d̄)², and lh_C_seg is
    not used by the hill_tan_reduced closure: flagged. The sidewall friction is identified."""
    text = """
[[parameters]]
key = "segregation.kappa"
lower = 0.5
upper = 2.0
scale = "log"

[[parameters]]
key = "segregation.kappa_T"
lower = 0.1
upper = 1.0
scale = "log"

[[parameters]]
key = "segregation.lh_C_seg"
lower = 0.05
upper = 0.5

[[parameters]]
key = "boundary.sidewall_friction"
lower = 0.2
upper = 0.4

[[cases]]
reference = "{ref}"
base = "{base}"
times = [0.025, 0.05]

[optimiser]
samples = 2
max_evaluations = 2
"""
    cal = write_cal(tmp_path, refs, text)
    out = tmp_path / "out"
    assert main(["calibrate", str(cal), "--out", str(out), "--workers", "2"]) == 0
    sens = json.loads((out / "sensitivity.json").read_text())
    assert sens["identified"] == ["boundary.sidewall_friction"]
    assert set(sens["unidentifiable"]) == {"segregation.kappa", "segregation.kappa_T",
                                           "segregation.lh_C_seg"}  # fmt: skip
    kinds = {(f["kind"], tuple(sorted(f["parameters"]))) for f in sens["flags"]}
    assert ("no_effect", ("segregation.lh_C_seg",)) in kinds
    combos = [f for f in sens["flags"] if f["kind"] == "combination"
              and set(f["parameters"]) >= {"segregation.kappa", "segregation.kappa_T"}]  # fmt: skip
    assert combos
    v = combos[0]["eigenvector"]
    assert v[0] == pytest.approx(-v[1], abs=0.05) and abs(v[3]) < 0.05  # ln κ − ln κ_T
    assert sens["jacobian_column_norms"]["boundary.sidewall_friction"] > 0
    assert sens["jacobian_column_norms"]["segregation.lh_C_seg"] == 0.0
    assert len(sens["eigenvalues"]) == 4 and len(sens["correlation"]) == 4


def _start(args: list[str], env: dict[str, str]) -> subprocess.Popen:
    return subprocess.Popen(args, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                            start_new_session=True)  # fmt: skip


def test_scheduler_and_worker_by_hand_then_predict(tmp_path, refs, capsys):
    """``dask scheduler`` and ``dask worker`` in their own processes, the calibration (differential
    evolution) through ``--scheduler``, then ``segmpm predict`` on a held-out case."""
    text = CAL_1P.replace('method = "lhs_then_local"', 'method = "differential_evolution"\n'
                          "popsize = 4\nmax_iterations = 2\npolish = true").replace(
                          "max_evaluations = 10", "max_evaluations = 9")  # fmt: skip
    cal = write_cal(tmp_path, refs, text)
    env = {**SUBPROCESS_ENV, "PYTHONPATH": os.pathsep.join(sys.path)}
    sfile = tmp_path / "scheduler.json"
    dask = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
    sched = _start([*dask, "--scheduler-file", str(sfile), "--no-dashboard", "--host",
                    "127.0.0.1", "--port", "0"], env)  # fmt: skip
    worker = None
    try:
        for _ in range(300):
            if sfile.exists() and sfile.stat().st_size > 0:
                break
            time.sleep(0.1)
        addr = json.loads(sfile.read_text())["address"]
        worker = _start([sys.executable, "-m", "distributed.cli.dask_worker", addr, "--nthreads",
                         "1", "--nworkers", "1", "--no-dashboard"], env)  # fmt: skip
        out = tmp_path / "out"
        assert main(["calibrate", str(cal), "--out", str(out), "--scheduler", addr]) == 0
        h = history(out)
        assert set(h["stage"].values) >= {"de", "sensitivity"}
        assert int((h["stage"] != "sensitivity").sum()) <= 9
        held = tmp_path / "heldout.toml"
        held.write_text(f'[[cases]]\nname = "steeper"\nreference = "{refs / "heldout.csv"}"\n'
                        f'base = "{refs / "base.toml"}"\nset = ["geometry.slope_deg=28.0"]\n'
                        "times = [0.025, 0.05]\n")  # fmt: skip
        assert main(["predict", str(out), "--cases", str(held), "--scheduler", addr]) == 0
    finally:
        for p in (worker, sched):
            if p is not None:
                os.killpg(p.pid, signal.SIGTERM)
                p.wait(timeout=30)
    xv = json.loads((out / "predict" / "crossval.json").read_text())
    rows = xv["rows"]
    assert {r["set"] for r in rows} == {"fit", "held-out"}
    assert [r["time"] for r in rows if r["set"] == "held-out"] == TIMES
    best = json.loads((out / "best.json").read_text())
    fit_terms = best["per_case"][0]["terms"]
    for r, f in zip([r for r in rows if r["set"] == "fit"], fit_terms, strict=True):
        assert r["phi_rms"] == f["phi_rms"] and r["u_rms_rel"] == f["u_rms_rel"]
    md = (out / "predict" / "crossval.md").read_text()
    assert "| held-out | steeper | 0.05 |" in md and "| fit | tiny | 0.025 |" in md
    mu = best["parameters"]["boundary.sidewall_friction"]
    assert math.isfinite(mu) and 0.1 <= mu <= 0.6
    # the same CAL on a local cluster of one worker: the same history (seeded evolution), and
    # calibrate --predict gives the same cross-validation
    out2 = tmp_path / "out2"
    args = ["calibrate", str(cal), "--out", str(out2), "--workers", "1", "--predict", str(held)]
    assert main(args) == 0
    _same_history(history(out2), history(out))
    rows2 = json.loads((out2 / "predict" / "crossval.json").read_text())["rows"]
    assert [(r["set"], r["case"], r["time"], r["phi_rms"]) for r in rows2] == [
        (r["set"], r["case"], r["time"], r["phi_rms"]) for r in rows]  # fmt: skip


@pytest.mark.skipif(not HAS_COLUMN, reason="scenario.solver (the column model) not in this segmpm")
def test_recovery_with_the_column_model(tmp_path):
    """Two parameters recovered within 5 % from a reference made by the column model itself."""
    (tmp_path / "base.toml").write_text(
        'extends = "chute_seed"\n[scenario]\nsolver = "column"\n[geometry]\ndepth = 0.01\n'
    )
    true = {"boundary.sidewall_friction": 0.3, "segregation.kappa_T": 0.3}
    cfg = load_config(tmp_path / "base.toml", [f"{k}={v}" for k, v in true.items()] + [
        "time.end=2.0", "output.profile_times=[0.0,1.0,2.0]", "output.fields=false",
        "output.figures=false", "output.progress=false"])  # fmt: skip
    Simulation(cfg, out_dir=tmp_path / "truth").run(progress=False)
    write_reference(tmp_path / "truth", tmp_path / "ref.csv")
    (tmp_path / "cal.toml").write_text("""
[[parameters]]
key = "boundary.sidewall_friction"
lower = 0.15
upper = 0.5
[[parameters]]
key = "segregation.kappa_T"
lower = 0.05
upper = 2.0
scale = "log"
[[cases]]
reference = "ref.csv"
base = "base.toml"
times = [1.0, 2.0]
[optimiser]
samples = 8
max_evaluations = 60
[inner]
model = "column"
""")
    out = tmp_path / "out"
    assert cal_mod.run_calibration(tmp_path / "cal.toml", out, workers=2) == 0
    best = json.loads((out / "best.json").read_text())["parameters"]
    for k, v in true.items():
        assert abs(best[k] - v) < 0.05 * v, (k, best[k])


def test_worked_example_files_are_valid():
    """examples/calibrate_seed.toml and calibrate_heldout.toml resolve (presets, DEM references,
    times, bounds) without running anything; with the column model on this segmpm, fully."""
    import tomllib

    from segmpm.calibrate.spec import CaseSpec, Parameter, read_cal, resolve_cases

    ex = Path(__file__).resolve().parents[1] / "examples"
    spec, _ = read_cal(ex / "calibrate_seed.toml")
    assert spec.inner.model == "column"
    assert [p.key for p in spec.parameters] == [
        "segregation.lh_C_seg", "segregation.lh_C_p", "segregation.lh_C_diff"]  # fmt: skip
    params = [Parameter(q.key, q.lower, q.upper, q.scale) for q in spec.parameters]
    solver = "column" if HAS_COLUMN else "mpm"
    cases = resolve_cases(spec.cases, ex, spec.objective.times, params, solver, spec.objective,
                          "example")  # fmt: skip
    assert cases[0].data["material"]["rheology"] == "nonlocal" and cases[0].times == [1, 5, 20]
    held = [CaseSpec.model_validate(c) for c in
            tomllib.loads((ex / "calibrate_heldout.toml").read_text())["cases"]]  # fmt: skip
    hc = resolve_cases(held, ex, [1.0], params, solver, spec.objective, "heldout")
    assert [c.name for c in hc] == ["muw015", "theta27"]
    mid = {p.key: p.to_x(0.5) for p in params}
    cfg = hc[0].config(mid, solver)
    assert cfg.boundary.sidewall_friction == pytest.approx(0.1567, abs=1e-4)
    assert hc[1].config(mid, solver).geometry.slope_deg == 27.0
