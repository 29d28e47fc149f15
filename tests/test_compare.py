"""``segmpm compare``: error norms against a reference CSV on synthetic data with known answers."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from segmpm.analysis.compare import compare_run, surface_velocity
from segmpm.analysis.profiles import PROFILE_VARIABLES
from segmpm.cli import main
from segmpm.io.profiles import ProfileWriter

EDGES = np.arange(11) * 1e-3  # ten 1 mm bins, centres 0.5 … 9.5 mm
Y = 0.5 * (EDGES[1:] + EDGES[:-1])
TOP = 8  # bins 0..7 hold material, 8 and 9 are empty (NaN)
RUN_TIMES = [0.0, 1.0, 20.0]
PHI0 = 0.45  # the run's well-mixed φ_s (its configuration)


def run_phi(y, t):
    return 0.2 + 40.0 * y + 0.01 * t  # linear in y: interpolation is exact


def run_u(y, t):
    return (1.0 + t) * 20.0 * y


def make_run(path):
    path.mkdir(parents=True, exist_ok=True)
    attrs = {"title": "synthetic", "configuration": f"[mixture]\nphi_small_initial = {PHI0}\n"}
    w = ProfileWriter(path / "profiles.nc", EDGES, attrs)
    for t in RUN_TIMES:
        prof = {k: np.full(len(Y), np.nan) for k in PROFILE_VARIABLES}
        prof["phi_small"][:TOP] = run_phi(Y[:TOP], t)
        prof["velocity_x"][:TOP] = run_u(Y[:TOP], t)
        w.add(t, prof)
    return path


# reference heights: between bin centres and inside the run's material (0.5 … 7.5 mm) plus two
# rows outside it (below the lowest centre, above the highest), which must be ignored
REF_Y = np.array([0.2e-3, 1.0e-3, 2.3e-3, 3.0e-3, 4.75e-3, 6.0e-3, 7.5e-3, 9.0e-3])
INSIDE = np.array([False, True, True, True, True, True, True, False])
DPHI = np.array([0.3, 0.05, -0.02, 0.04, -0.01, 0.03, -0.06, 0.4])  # run - reference
DU = np.array([0.5, 0.002, 0.001, -0.003, 0.0, 0.001, 0.002, 0.5])


def write_reference(path, times=(1.0, 20.0, 5.0), y_shift=0.0, header=None, extra_rows=()):
    lines = ["# synthetic reference", "# datum: base"]
    lines.append(header or "time_s,y_m,phi_small,velocity_x,n_particles")
    for t in times:
        for y, dp, du in zip(REF_Y, DPHI, DU, strict=True):
            lines.append(
                f"{t:g},{y - y_shift:.9g},{run_phi(y, t) - dp:.12g},{run_u(y, t) - du:.12g},100"
            )
    lines.extend(extra_rows)
    path.write_text("\n".join(lines) + "\n")
    return path


def expected(t):
    """The norms over the whole depth of the reference: the two rows outside the run's bins are
    compared with the run's value at its nearest bin centre (0.5 mm below, 7.5 mm above)."""
    ext_y = np.clip(REF_Y, Y[0], Y[TOP - 1])
    dphi = run_phi(ext_y, t) - (run_phi(REF_Y, t) - DPHI)
    du = run_u(ext_y, t) - (run_u(REF_Y, t) - DU)
    u_ref = run_u(REF_Y, t) - DU
    us_ref = np.mean(u_ref[-2:])  # the two highest reference rows with data
    phi_ref = run_phi(REF_Y, t) - DPHI
    mixed = math.sqrt(np.mean((phi_ref - PHI0) ** 2))
    return {
        "phi_rms": math.sqrt(np.mean(dphi**2)),
        "phi_max": np.max(np.abs(dphi)),
        "u_rms": math.sqrt(np.mean(du**2)),
        "u_rms_rel": math.sqrt(np.mean(du**2)) / abs(us_ref),
        "phi_rms_overlap": math.sqrt(np.mean(DPHI[INSIDE] ** 2)),
        "u_rms_rel_overlap": math.sqrt(np.mean(DU[INSIDE] ** 2)) / abs(us_ref),
        "phi_rms_mixed": mixed,
        "segregation_skill": 1 - math.sqrt(np.mean(dphi**2)) / mixed,
        "u_surface_reference": us_ref,
        "u_surface_run": np.mean(run_u(Y[TOP - 2 : TOP], t)),
        "n_phi": len(REF_Y),
        "n_phi_outside": int((~INSIDE).sum()),
    }


@pytest.fixture
def run_dir(tmp_path):
    return make_run(tmp_path / "run")


def test_norms_equal_analytic_values(run_dir, tmp_path, capsys):
    ref = write_reference(tmp_path / "ref.csv")
    assert compare_run(run_dir, ref) == 0
    out = capsys.readouterr().out
    assert "rms dphi" in out
    data = json.loads((run_dir / "compare.json").read_text())
    assert data["times"] == [1.0, 20.0]  # common times only (0 not in ref, 5 not in run)
    assert data["y_offset"] == 0.0
    assert data["reference"].endswith("ref.csv")
    for t in (1.0, 20.0):
        got = data["per_time"][f"{t:g}"]
        for k, v in expected(t).items():
            assert got[k] == pytest.approx(v, rel=1e-9, abs=1e-12), (t, k)
        assert got["n_velocity"] == len(REF_Y)
    assert (run_dir / "figures" / "compare.png").stat().st_size > 1000


def test_y_offset_and_selected_times(run_dir, tmp_path):
    ref = write_reference(tmp_path / "ref.csv", y_shift=0.7e-3)  # reference datum 0.7 mm higher
    assert main(["compare", str(run_dir), str(ref), "--times", "20", "--y-offset", "0.0007"]) == 0
    data = json.loads((run_dir / "compare.json").read_text())
    assert data["times"] == [20.0] and list(data["per_time"]) == ["20"]
    assert data["y_offset"] == pytest.approx(7e-4)
    for k, v in expected(20.0).items():
        assert data["per_time"]["20"][k] == pytest.approx(v, rel=1e-9, abs=1e-12), k


def test_missing_values_in_reference_are_skipped(run_dir, tmp_path):
    # an extra row at a time with an empty velocity cell: compared for phi only
    ref = write_reference(tmp_path / "ref.csv", times=(1.0,), extra_rows=["1,0.004,0.5,,3"])
    assert compare_run(run_dir, ref) == 0
    got = json.loads((run_dir / "compare.json").read_text())["per_time"]["1"]
    assert got["n_phi"] == len(REF_Y) + 1 and got["n_velocity"] == len(REF_Y)
    dphi = np.append(DPHI[INSIDE], run_phi(0.004, 1.0) - 0.5)
    assert got["phi_rms_overlap"] == pytest.approx(math.sqrt(np.mean(dphi**2)), rel=1e-9)


def test_surface_velocity_definition():
    y = np.array([3.0, 1.0, 2.0, 4.0, 5.0])
    u = np.array([3.0, 1.0, 2.0, 4.0, np.nan])
    assert surface_velocity(y, u) == pytest.approx(3.5)  # mean of the two highest with data
    assert surface_velocity(y[:1], u[:1]) == 3.0
    assert math.isnan(surface_velocity(y, np.full(5, np.nan)))


def _fails(capsys, argv, *needles):
    assert main(argv) == 2
    err = capsys.readouterr().err
    for n in needles:
        assert n in err, err
    assert "Traceback" not in err
    return err


def test_errors_exit_2_naming_the_problem(run_dir, tmp_path, capsys):
    ref = write_reference(tmp_path / "ref.csv")
    # missing files
    _fails(capsys, ["compare", str(tmp_path / "nope"), str(ref)], "nope", "does not exist")
    empty = tmp_path / "empty_run"
    empty.mkdir()
    _fails(capsys, ["compare", str(empty), str(ref)], "profiles.nc")
    _fails(capsys, ["compare", str(run_dir), str(tmp_path / "missing.csv")], "missing.csv")
    # bad columns
    bad = write_reference(tmp_path / "bad.csv", header="time_s,y,phi_small,u,n")
    _fails(capsys, ["compare", str(run_dir), str(bad)], "bad.csv", "y_m", "velocity_x")
    # unparsable value
    garbled = write_reference(tmp_path / "garbled.csv", extra_rows=["1,abc,0.5,0.1,1"])
    _fails(capsys, ["compare", str(run_dir), str(garbled)], "garbled.csv", "y_m", "abc", "line")
    only_comments = tmp_path / "comments.csv"
    only_comments.write_text("# nothing\n")
    _fails(capsys, ["compare", str(run_dir), str(only_comments)], "comments.csv", "time_s")
    # unknown time: listed availability
    _fails(capsys, ["compare", str(run_dir), str(ref), "--times", "1", "7"], "t = 7", "0, 1, 20")
    _fails(
        capsys,
        ["compare", str(run_dir), str(ref), "--times", "0"],
        "t = 0",
        "reference",
        "1, 5, 20",
    )
    # no common time
    other = write_reference(tmp_path / "other.csv", times=(3.0,))
    _fails(capsys, ["compare", str(run_dir), str(other)], "no time in common")
    # offset that moves the reference out of the material
    _fails(capsys, ["compare", str(run_dir), str(ref), "--y-offset", "1"], "--y-offset")
    # a file that is not NetCDF
    (empty / "profiles.nc").write_text("not netcdf")
    _fails(capsys, ["compare", str(empty), str(ref)], "profiles.nc", "cannot be read")
    assert not (run_dir / "compare.json").exists()
