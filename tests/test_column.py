"""The column model (``scenario.solver = "column"``): its step against the NumPy twin, the
steady sidewall chute against the closed form, the 2-D MPM on the same layer, conservation,
resume, and the configuration check."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import make_sim

from segmpm.analysis.closed_form import bagnold_velocity, sidewall_velocity
from segmpm.column import COL_U, COL_Y, build_column, column_step_np
from segmpm.config import ConfigError, load_config
from segmpm.engine.records import XX, XY, YY, ZZ
from segmpm.mpm import params as mpp

COLUMN = ["scenario.solver='column'"]
#: a thin layer of the seed preset (8 mm, the 2 mm / 3 mm mixture), quick for both solvers
THIN = ["geometry.depth=0.008", "geometry.length=0.001"]
NONLOCAL = ["material.rheology='nonlocal'", "material.q_phi=0.75", "material.static_friction=0.36537",
            "material.rate_sensitivity=0.38246", "material.nonlocal_amplitude=0.48953",
            "material.fluidity_time=1e-3", "segregation.model='liu_henann'"]  # fmt: skip

CASES = {
    "local-eq6": [*THIN],
    "nonlocal-lh-rate-wall": [
        *THIN,
        *NONLOCAL,
        "material.fluidity_dt=1e-9",
        "boundary.sidewall_friction_slow=0.1",
        "boundary.sidewall_slip_speed=0.05",
    ],  # fmt: skip
    "elastic-friction-base": [
        *THIN,
        "material.model='linear_elastic'",
        "boundary.base='friction'",
        "boundary.base_friction=0.3",
    ],  # fmt: skip
}


#: the twin's tensor rows (xx, yy, xy, zz) in the engine's (xx, yy, zz, xy)
TO_TWIN = [XX, YY, XY, ZZ]
#: the twin's scalar slots S_* of the engine clock's fields (same names, lower case)
SLOTS = {getattr(mpp, "S_" + name.upper()): name
         for name in ("time", "step", "tseg", "smax", "numax", "dt", "nseg", "tflu", "nflu")}  # fmt: skip


def _twin_layout(sim) -> dict[str, np.ndarray]:
    """The state of a column run in the layout that ``column_step_np`` reads (segmpm.state)."""
    P = sim.engine.points
    out = {k: getattr(P, k).copy() for k in ("x", "v", "mass", "vol0", "J", "phi", "gf", "diag",
                                            "s_int", "g_int")}  # fmt: skip
    out["eps"], out["sig"] = P.eps[TO_TWIN].copy(), P.sig[TO_TWIN].copy()
    out["nodes"] = sim.engine.nodes.copy()
    out["sc"] = np.zeros(mpp.S_NSLOTS)
    for slot, name in SLOTS.items():
        out["sc"][slot] = sim.clock[name]
    return out


@pytest.mark.parametrize("case", sorted(CASES))
def test_one_column_step_matches_numpy_reference(case, rng):
    """One step of the engine's compiled column (a sheared, slightly compressed column with
    random fluidity and φ_s) is the NumPy twin's to round-off. The twin reads the layout and
    grid record of segmpm.state (``column.build_column``); the engine's state is translated into
    it."""
    over = [*COLUMN, *CASES[case], "boundary.ramp_time=0.1"]
    sim = make_sim(over)
    twin = build_column(sim.config)  # the twin's grid and material records
    P = sim.engine.points
    n = sim.engine.n
    sim.engine.nodes[COL_U, 1:] = rng.uniform(0.0, 0.1, n)
    sim.engine.nodes[COL_U + 1, 1:] = rng.normal(scale=1e-3, size=n)
    P.eps[XY] += rng.normal(scale=1e-6, size=n)
    P.phi[:] = rng.uniform(0, 1, n)
    P.gf[:] = rng.uniform(0, 50, n)
    sim.prime()
    before = _twin_layout(sim)
    ref = column_step_np(before, twin.gp, twin.mp)
    status, _, n = sim.advance(1.0, 1)
    assert status == 0 and n == 1
    after = _twin_layout(sim)
    for k, b in ref.items():
        scale = max(np.max(np.abs(b)), 1e-300)
        np.testing.assert_allclose(after[k], b, rtol=0, atol=1e-11 * scale, err_msg=k)
    assert np.max(np.abs(after["nodes"][COL_U] - before["nodes"][COL_U])) > 0
    assert np.max(np.abs(after["sig"] - before["sig"])) > 0


def _steady(over: list[str], t_end: float):
    sim = make_sim([*COLUMN, *over, f"time.end={t_end}"])
    sim.advance_to(t_end)
    return sim


@pytest.mark.parametrize(
    "theta, H, mu_w, t_end", [(26.0, 0.006, 0.0, 0.6), (26.0, 0.012, 0.3, 0.8)]
)
def test_steady_chute_matches_the_local_closed_forms(theta, H, mu_w, t_end):
    """The steady Bagnold layer and the sidewall chute of the Fei model (μ_eff = q_c + a I,
    segregation off, docs/model.md §3): the column's nodal velocities against the closed forms
    (``analysis.closed_form``): surface speed within 1 %, profile RMS within 1 % of it; a static
    bed below the sidewall chute's flowing depth ζ_f."""
    over = [f"geometry.slope_deg={theta}", f"geometry.depth={H}", "segregation.model='none'",
            f"boundary.sidewall_friction={mu_w}", "material.stiffness_scale=1e-3"]  # fmt: skip
    sim = _steady(over, t_end)
    y, u = sim.engine.nodes[COL_Y], sim.engine.nodes[COL_U]
    if mu_w == 0.0:
        th, zf = bagnold_velocity(sim.config, y), H
    else:
        th, zf = sidewall_velocity(sim.config, y)
    assert th[-1] > 0.01
    assert abs(u[-1] / th[-1] - 1) < 0.01, (u[-1], th[-1])
    assert np.sqrt(np.mean((u - th) ** 2)) / th[-1] < 0.01
    bed = y < H - zf - 1.0e-3
    if mu_w > 0.0:
        assert bed.sum() > 3 and np.max(np.abs(u[bed])) < 1e-3 * th[-1]


def test_column_and_mpm_agree_on_the_seed_layer():
    """The column against the 2-D MPM (1-cell periodic strip) on a thin seed layer with
    segregation: surface speed within 1 %, velocity RMS ≤ 0.01 u_s, φ_s RMS ≤ 0.02 at 0.5 s."""
    over = [*THIN, "time.end=0.5"]
    prof = {}
    for solver in ("column", "mpm"):
        sim = make_sim([f"scenario.solver='{solver}'", *over])
        sim.advance_to(0.5)
        prof[solver] = sim.profiles()
    c, m = prof["column"], prof["mpm"]
    ok = np.isfinite(c["velocity_x"]) & np.isfinite(m["velocity_x"])
    us = float(np.nanmax(m["velocity_x"]))
    assert us > 0.01
    assert abs(np.nanmax(c["velocity_x"]) - us) / us < 0.01
    assert np.sqrt(np.mean((c["velocity_x"][ok] - m["velocity_x"][ok]) ** 2)) / us <= 0.01
    assert np.sqrt(np.mean((c["phi_small"][ok] - m["phi_small"][ok]) ** 2)) <= 0.02
    # segregation happened (the comparison is not of two well-mixed layers)
    assert np.nanmax(np.abs(m["phi_small"] - 0.5)) > 0.05


def test_column_conserves_mass_and_small_grains_and_keeps_bounds():
    sim = _steady([*THIN, *NONLOCAL], 0.5)
    c = sim.conservation()
    assert c["mass_drift"] == 0.0
    assert abs(c["small_volume_drift"]) < 1e-12
    P = sim.engine.points
    assert np.all((P.phi >= 0.0) & (P.phi <= 1.0))
    assert np.all(np.isfinite(P.gf)) and np.max(P.gf) > 0.0
    assert sim.engine.nodes[COL_U, 0] == 0.0  # the no-slip base


def test_column_resume_is_bit_identical(tmp_path):
    """A column run stopped at a checkpoint and resumed ends in the state of one uninterrupted
    run, bit for bit (every checkpointed array, the clock's step count included), with the
    same profile times and profiles, and writes no particle snapshots."""
    over = [*COLUMN, *THIN, *NONLOCAL, "time.end=0.1", "output.checkpoint_interval=0.05",
            "output.profile_times=[0.0, 0.05, 0.1]"]  # fmt: skip
    a = make_sim(over, out_dir=tmp_path / "a")
    assert a.run().exit_code == 0
    b = make_sim([*over, "time.end=0.05"], out_dir=tmp_path / "b")
    assert b.run().exit_code == 0
    c = make_sim(over, out_dir=tmp_path / "b")
    assert c.run(resume=True).exit_code == 0
    assert a.steps == c.steps
    for k, arr in a.engine.arrays().items():
        np.testing.assert_array_equal(arr, c.engine.arrays()[k], err_msg=k)
    assert np.max(a.engine.points.gf) > 0.0
    import xarray as xr

    with (
        xr.open_dataset(tmp_path / "a" / "profiles.nc", engine="h5netcdf") as pa,
        xr.open_dataset(tmp_path / "b" / "profiles.nc", engine="h5netcdf") as pb,
    ):
        assert pa["time"].values.tolist() == pb["time"].values.tolist() == [0.0, 0.05, 0.1]
        np.testing.assert_array_equal(pa["velocity_x"].values, pb["velocity_x"].values)
    assert not (tmp_path / "a" / "fields").exists() or not any(
        (tmp_path / "a" / "fields").iterdir()
    )


def test_column_needs_a_chute():
    with pytest.raises(ConfigError, match="scenario.solver"):
        load_config(
            preset="chute_seed",
            overrides=[*COLUMN, "scenario.kind='collapse'", "geometry.length=0.04"],
        )


def test_column_time_step_is_its_combined_courant_step_on_its_element():
    """Δt = min(C Δy/(max(c + |v|) + 2 max ν/Δy), C_ν Δy²/(2 max ν)) with C =
    time.column_courant on the shortest element (the wave speed and viscosity of the last step,
    the wave speed never below the loaded material's floor)."""
    sim = make_sim([*COLUMN, *THIN, "time.end=0.01", "time.column_courant=0.6"])
    sim.advance_to(0.001)
    dy = float(np.min(np.diff(sim.engine.nodes[COL_Y])))
    smax = max(float(sim.clock["smax"]), float(sim.engine.prm[0]["c_floor"]))
    nu = float(sim.clock["numax"])
    assert nu > 0.0  # the local law's σ^d and the column's bulk viscosity
    want = min(0.6 * dy / (smax + 2.0 * nu / dy), sim.config.time.viscous_number * dy**2 / (2 * nu))
    sim.advance(1.0, 1)
    assert sim.clock["dt"] == pytest.approx(want, rel=1e-12)
    assert dy == pytest.approx(sim.config.grid.cell_size / 2, rel=0.02)  # n_ppc = 2


def test_every_profile_time_is_written_when_checkpoints_fall_on_them(tmp_path):
    """Ten checkpoints of 0.1 s do not sum to 1.0 s exactly; the output at 1.0 s (and at 0.3 s,
    where 3 × 0.1 lies above) must still be written, once each (found on the stiffness study,
    whose 1 s profile was missing)."""
    import xarray as xr

    times = [0.0, 0.3, 0.7, 1.0]
    sim = make_sim([*COLUMN, *THIN, "time.end=1.0", "output.checkpoint_interval=0.1",
                    f"output.profile_times={times!r}"], out_dir=tmp_path)  # fmt: skip
    assert sim.run().exit_code == 0
    with xr.open_dataset(tmp_path / "profiles.nc", engine="h5netcdf") as ds:
        assert ds["time"].values.tolist() == times


def test_column_runs_from_the_command_line_without_particle_snapshots(tmp_path):
    """`segmpm run PRESET --set scenario.solver="column"`: the ordinary outputs (profiles, run.json,
    checkpoint, config), no particle snapshots even with output.fields = true, and `plot` works."""
    from segmpm.cli import main

    out = tmp_path / "col"
    args = ["run", "chute_nonlocal", "--out", str(out), "--no-progress"]
    for s in ("scenario.solver='column'", "time.end=0.05", "output.fields=true",
              "output.profile_times=[0.0, 0.05]", *THIN):  # fmt: skip
        args += ["--set", s]
    assert main(args) == 0
    for f in ("profiles.nc", "run.json", "config.toml", "checkpoint/state.npz"):
        assert (out / f).is_file(), f
    assert not (out / "fields").exists() or not any((out / "fields").iterdir())
    assert 'solver = "column"' in (out / "config.toml").read_text()
    assert main(["plot", str(out)]) == 0
