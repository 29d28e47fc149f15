"""``segmpm sweep``: a tiny ensemble on a local dask cluster, re-run skipping, input errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
import xarray as xr

from segmpm.cli import main
from segmpm.sweep import build_members, run_sweep

BASE = """
[scenario]
kind = "chute"
[geometry]
depth = 0.003
length = 0.002
[material]
stiffness_scale = 1e-3
[time]
end = 0.01
[output]
profile_times = [0.0, 0.01]
fields = false
figures = false
progress = false
[segregation]
model = "none"
"""


def write_sweep(tmp_path, parameters: str, mode: str = "", inline: bool = False, base=BASE):
    if inline:
        head = base.replace("\n[", "\n[base.")
    else:
        (tmp_path / "base.toml").write_text(base)
        head = 'base = "base.toml"\n'
    text = (f'mode = "{mode}"\n' if mode else "") + head + "\n[parameters]\n" + parameters
    path = tmp_path / "sweep.toml"
    path.write_text(text)
    return path


def surface_velocity(ds: xr.Dataset, member: int) -> float:
    u = ds["velocity_x"].isel(member=member, time=-1).values
    return float(u[np.isfinite(u)][-2:].mean())


def test_sweep_runs_gathers_and_skips_completed(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the base file is found relative to the sweep file, not the cwd
    sweep = write_sweep(tmp_path, '"geometry.slope_deg" = [15.0, 35.0]\n')
    out = tmp_path / "out"
    assert run_sweep(sweep, out, None, 1) == 0
    with xr.open_dataset(out / "ensemble.nc", engine="h5netcdf") as ds:
        ds = ds.load()
    assert ds.sizes["member"] == 2
    assert list(ds["member"].values) == [0, 1]
    assert list(ds["geometry.slope_deg"].values) == [15.0, 35.0]
    assert ds["geometry.slope_deg"].dims == ("member",)
    assert list(ds["status"].values) == ["completed", "completed"]
    assert ds["velocity_x"].dims == ("member", "time", "y")
    assert list(ds["time"].values) == [0.0, 0.01]
    assert "slope_deg = 35.0" in str(ds["configuration"].values[1])
    assert surface_velocity(ds, 1) > surface_velocity(ds, 0) + 1e-3  # 35° flows, 15° does not
    manifest = json.loads((out / "sweep.json").read_text())
    assert [m["parameters"] for m in manifest["members"]] == [
        {"geometry.slope_deg": 15.0},
        {"geometry.slope_deg": 35.0},
    ]
    # the members are ordinary runs
    for i in (0, 1):
        info = json.loads((out / "members" / f"{i:04d}" / "run.json").read_text())
        assert info["status"] == "completed"
    mtimes = [(out / "members" / f"{i:04d}" / "run.json").stat().st_mtime_ns for i in (0, 1)]
    # re-running skips the completed members (no cluster needed) and rewrites the ensemble
    assert main(["sweep", str(sweep), "--out", str(out), "--workers", "1"]) == 0
    assert [
        (out / "members" / f"{i:04d}" / "run.json").stat().st_mtime_ns for i in (0, 1)
    ] == mtimes
    with xr.open_dataset(out / "ensemble.nc", engine="h5netcdf") as ds2:
        assert list(ds2["status"].values) == ["completed", "completed"]
        np.testing.assert_array_equal(ds2["velocity_x"].values, ds["velocity_x"].values)
    assert all(
        m["action"] == "skip" for m in json.loads((out / "sweep.json").read_text())["members"]
    )


def test_failed_member_exit_3(tmp_path, capsys):
    # dt_min above the CFL step: the run fails at once with a time-step collapse
    sweep = write_sweep(
        tmp_path, '"time.dt_min" = [9e-4]\n"time.dt_max" = [1e-3]\n', mode="zip", inline=True
    )
    assert run_sweep(sweep, tmp_path / "out", None, 1) == 3
    err = capsys.readouterr().err
    assert "0000" in err and "failed" in err
    with xr.open_dataset(tmp_path / "out" / "ensemble.nc", engine="h5netcdf") as ds:
        assert list(ds["status"].values) == ["failed"]
        assert ds["time.dt_min"].values.tolist() == [9e-4]


def test_members_product_and_zip_order(tmp_path):
    sweep = write_sweep(
        tmp_path, '"segregation.c_D" = [4.0, 6.8]\n"geometry.slope_deg" = [20, 30]\n'
    )
    members, meta = build_members(sweep, tmp_path / "out")
    assert meta["mode"] == "product" and meta["parameters"] == [
        "segregation.c_D",
        "geometry.slope_deg",
    ]
    assert [tuple(m.params.values()) for m in members] == [
        (4.0, 20),
        (4.0, 30),
        (6.8, 20),
        (6.8, 30),
    ]
    assert members[3].config.segregation.c_D == 6.8 and members[3].config.geometry.slope_deg == 30
    assert members[3].dir == tmp_path / "out" / "members" / "0003"
    sweep = write_sweep(
        tmp_path, '"segregation.c_D" = [4.0, 6.8]\n"geometry.slope_deg" = [20, 30]\n', mode="zip"
    )
    members, _ = build_members(sweep, tmp_path / "out")
    assert [tuple(m.params.values()) for m in members] == [(4.0, 20), (6.8, 30)]


@pytest.mark.parametrize(
    "parameters, mode, needles",
    [
        (
            '"geometry.slope_deg" = [20.0, 30.0]\n"segregation.c_D" = [4.0]\n',
            "zip",
            ["zip", "geometry.slope_deg: 2", "segregation.c_D: 1"],
        ),  # fmt: skip
        ('"geometry.slop_deg" = [20.0]\n', "", ["member 0000", "geometry.slop_deg"]),
        ('"geom.slope_deg" = [20.0]\n', "", ["geom.slope_deg", "unknown section"]),
        ('"slope_deg" = [20.0]\n', "", ["slope_deg", "section.key"]),
        ('"geometry.slope_deg" = 20.0\n', "", ["geometry.slope_deg", "non-empty list"]),
        ('"geometry.slope_deg" = []\n', "", ["geometry.slope_deg", "non-empty list"]),
        (
            '"geometry.slope_deg" = [20.0, 95.0]\n',
            "",
            ["member 0001", "geometry.slope_deg", "< 90"],
        ),
        ('"geometry.slope_deg" = [20.0]\n', "diagonal", ["mode", "diagonal"]),
    ],
)
def test_invalid_sweeps_exit_2_before_running(tmp_path, capsys, parameters, mode, needles):
    sweep = write_sweep(tmp_path, parameters, mode=mode)
    out = tmp_path / "out"
    assert main(["sweep", str(sweep), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    for n in needles:
        assert n in err, err
    assert "Traceback" not in err
    assert not (out / "members").exists()  # nothing started


def test_invalid_sweep_files_exit_2(tmp_path, capsys):
    assert main(["sweep", str(tmp_path / "none.toml")]) == 2
    assert "none.toml" in capsys.readouterr().err
    p = tmp_path / "s.toml"
    p.write_text('base = "missing.toml"\n[parameters]\n"time.end" = [0.1]\n')
    assert main(["sweep", str(p), "--out", str(tmp_path / "o")]) == 2
    assert "missing.toml" in capsys.readouterr().err
    p.write_text('bse = "x.toml"\n')
    assert main(["sweep", str(p), "--out", str(tmp_path / "o")]) == 2
    assert "'bse'" in capsys.readouterr().err
    p.write_text("[parameters\n")
    assert main(["sweep", str(p), "--out", str(tmp_path / "o")]) == 2
    assert "not valid TOML" in capsys.readouterr().err


@pytest.mark.parametrize("inline", [False, True])
def test_sweep_base_may_extend_a_preset(tmp_path, inline):
    """A base (a file or an inline [base]) that ``extends`` the seed preset resolves onto it: the
    keys it does not set are the preset's, not the schema's defaults."""
    from segmpm.config import load_config

    base = 'extends = "chute_seed"\n[time]\nend = 0.01\n'
    if inline:
        text = '[base]\nextends = "chute_seed"\n[base.time]\nend = 0.01\n'
    else:
        (tmp_path / "base.toml").write_text(base)
        text = 'base = "base.toml"\n'
    path = tmp_path / "sweep.toml"
    path.write_text(text + '[parameters]\n"geometry.slope_deg" = [24.0, 26.0]\n')
    members, _ = build_members(path, tmp_path / "out")
    preset = load_config(preset="chute_seed")
    for m, slope in zip(members, (24.0, 26.0), strict=True):
        assert m.config.geometry.slope_deg == slope and m.config.time.end == 0.01
        assert m.config.material.stiffness_scale == preset.material.stiffness_scale == 1e-3
        assert m.config.geometry.length == preset.geometry.length
