"""Configuration validation and the command line: every invalid input exits 2 naming the key."""

from __future__ import annotations

import tomllib

import pytest

from segmpm.cli import main
from segmpm.config import ConfigError, load_config


def _write(tmp_path, text: str):
    p = tmp_path / "case.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize(
    "text, key, fragment",
    [
        ("[geometry]\nslop_deg = 20\n", "geometry.slop_deg", "unknown key"),
        ("[geometri]\nslope_deg = 20\n", "geometri", "unknown section"),
        ("[geometry]\nslope_deg = 'steep'\n", "geometry.slope_deg", "'steep'"),
        ("[geometry]\nslope_deg = 95.0\n", "geometry.slope_deg", "< 90"),
        ("[mixture]\nphi_small_initial = 1.5\n", "mixture.phi_small_initial", "≤ 1"),
        ("[grid]\ncell_size = -0.001\n", "grid.cell_size", "> 0"),
        ("[time]\nend = nan\n", "time.end", "nan"),
        ("[segregation]\nmodel = 'magic'\n", "segregation.model", "hill_tan_reduced"),
        ("[geometry]\nlength = 0.0123\n", "geometry.length", "whole number"),
        ("[grid]\ncell_size = 1e-7\n", "grid.cell_size", "material points"),
        ("[output]\nprofile_times = [1.0, 0.5]\n", "output.profile_times", "increasing"),
        ("[geometry\nslope_deg = 20\n", "case.toml", "not valid TOML"),
    ],
)
def test_validate_rejects_with_key_named(tmp_path, capsys, text, key, fragment):
    path = _write(tmp_path, text)
    assert main(["validate", str(path)]) == 2
    err = capsys.readouterr().err
    assert key in err and fragment in err, err
    assert "Traceback" not in err
    # `run` refuses the same file before starting
    assert main(["run", str(path), "--out", str(tmp_path / "o")]) == 2
    assert not (tmp_path / "o" / "run.json").exists()


def test_missing_file_exit_2(tmp_path, capsys):
    assert main(["validate", str(tmp_path / "nope.toml")]) == 2
    assert "does not exist" in capsys.readouterr().err


@pytest.mark.parametrize(
    "override, fragment",
    [
        ("geometry.slope_deg", "section.key=value"),
        ("slope_deg=20", "section.key"),
        ("nosuch.key=1", "unknown section 'nosuch'"),
        ("geometry.depth=", "missing value"),
        ("geometry.depth=[1,", "not valid TOML"),
        ("geometry.depth=-1", "geometry.depth"),
        ("material.stiffness_scale=0", "material.stiffness_scale"),
        ("time.cfl=2", "time.cfl"),
        ("grid.particles_per_cell=[2,3,3]", "grid.particles_per_cell = [2, 3, 3] has 3 counts"),
        ("grid.particles_per_cell=[2,7]", "less than or equal to 6"),
    ],
)
def test_bad_overrides_exit_2(capsys, override, fragment):
    assert main(["run", "--set", override, "--out", "/tmp/segmpm-never"]) == 2
    err = capsys.readouterr().err
    assert fragment in err, err


def test_validate_prints_resolved_configuration(tmp_path, capsys):
    path = _write(tmp_path, "[geometry]\nslope_deg = 24.0\n")
    assert main(["validate", str(path), "--set", "time.end=0.5"]) == 0
    out = capsys.readouterr().out
    data = tomllib.loads(out)
    assert data["geometry"]["slope_deg"] == 24.0
    assert data["time"]["end"] == 0.5
    assert data["material"]["A"] == 1.79e9  # defaults are filled in


def test_overrides_apply_before_validation():
    cfg = load_config(overrides=["geometry.slope_deg=24", "segregation.model=none"])
    assert cfg.geometry.slope_deg == 24 and cfg.segregation.model == "none"
    with pytest.raises(ConfigError, match="geometry.slope_deg"):
        load_config(overrides=["geometry.slope_deg=90"])


def test_help_and_version(capsys):
    assert main(["--help"]) == 0
    assert "segmpm" in capsys.readouterr().out
    assert main([]) == 0


def test_a_file_extends_a_preset_or_another_file(tmp_path):
    from segmpm.config import ConfigError, load_config

    (tmp_path / "a.toml").write_text('extends = "chute_seed"\n[time]\nend = 0.05\n')
    a = load_config(tmp_path / "a.toml")
    assert a.time.end == 0.05 and a.geometry.length == 0.001  # the preset's strip, not 12 mm
    (tmp_path / "b.toml").write_text('extends = "a.toml"\n[geometry]\nslope_deg = 24.0\n')
    b = load_config(tmp_path / "b.toml")
    assert b.time.end == 0.05 and b.geometry.slope_deg == 24.0
    (tmp_path / "c.toml").write_text("[time]\nend = 0.05\n")
    assert load_config(tmp_path / "c.toml").geometry.length == 0.012  # no extends: the schema
    (tmp_path / "d.toml").write_text('extends = "nope"\n')
    with pytest.raises(ConfigError, match="no such preset"):
        load_config(tmp_path / "d.toml")
    (tmp_path / "e.toml").write_text('extends = "e.toml"\n')
    with pytest.raises(ConfigError, match="levels of extends"):
        load_config(tmp_path / "e.toml")


def test_a_file_without_extends_is_named_as_starting_from_the_schema(tmp_path, capsys):
    """`validate` of a file that does not say what it extends notes that the unset keys are the
    schema's, not the preset's; a file that extends the preset gets no such note."""
    bare = tmp_path / "bare.toml"
    bare.write_text("[time]\nend = 0.05\n")
    assert main(["validate", str(bare)]) == 0
    assert "has no `extends`" in capsys.readouterr().err
    on_preset = tmp_path / "mine.toml"
    on_preset.write_text('extends = "chute_seed"\n[time]\nend = 0.05\n')
    assert main(["validate", str(on_preset)]) == 0
    assert "has no `extends`" not in capsys.readouterr().err


def test_the_default_is_the_nonlocal_preset_and_the_seed_model_a_preset_away(tmp_path, capsys):
    """The built-in default is ``chute_nonlocal`` (resolved onto ``chute_seed``); the seed's local
    model is the preset ``chute_seed``, reachable as the CONFIG argument; the seed's Eq. 6 is one
    ``--set`` from the default; a file of the same name wins over a preset name."""
    import os

    from segmpm.config import DEFAULT_PRESET, load_config

    assert DEFAULT_PRESET == "chute_nonlocal"
    d = load_config()
    assert d == load_config(preset="chute_nonlocal")
    assert d.material.rheology == "nonlocal" and d.segregation.model == "liu_henann"
    assert d.geometry.depth == 0.0373 and d.geometry.slope_deg == 26.0  # the seed's geometry
    seed = load_config("chute_seed")
    assert seed == load_config(preset="chute_seed")
    assert seed.material.rheology == "local" and seed.segregation.model == "hill_tan_reduced"
    eq6 = load_config(overrides=['segregation.model="hill_tan_reduced"'])
    assert eq6.segregation.driver == seed.segregation.driver == "B"
    assert eq6.segregation.c_D == seed.segregation.c_D and eq6.material.rheology == "nonlocal"
    with pytest.raises(ConfigError, match="not both"):
        load_config("chute_seed", preset="chute_seed")
    assert main(["validate", "chute_seed"]) == 0
    assert 'rheology = "local"' in capsys.readouterr().out
    assert main(["validate", "no_such_preset"]) == 2
    cwd = os.getcwd()
    try:  # a file named like a preset (with .toml) is a file
        os.chdir(tmp_path)
        (tmp_path / "chute_seed.toml").write_text('extends = "chute_seed"\n[time]\nend = 0.05\n')
        assert load_config("chute_seed.toml").time.end == 0.05
    finally:
        os.chdir(cwd)
