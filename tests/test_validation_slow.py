"""Slow validation, skipped in CI (run with `python -m pytest -m slow`)."""

from __future__ import annotations

import importlib.util
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]


def _load(name: str):
    spec = importlib.util.spec_from_file_location(name, ROOT / "validation" / f"{name}.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.slow
@pytest.mark.parametrize(
    "aspect",
    [
        # known deficit (docs/validation.md §2): the runout is 20.1 % short at a = 0.5, converged
        # in h and independent of the base; a property of the unbounded μ_eff = q_c + a I
        pytest.param(
            0.5,
            marks=pytest.mark.xfail(reason="known 20.1 % short runout at a = 0.5", strict=False),
        ),  # fmt: skip
        2.0,
        6.0,
    ],
)
def test_collapse_runout_within_20_percent_of_experiments(aspect):
    """Lube et al. 2005 / Lajeunesse et al. 2005 scaling (docs/validation.md §2)."""
    r = _load("collapse_runout").run(aspect)
    assert abs(r["relative_error"]) < 0.2, r
    assert r["kinetic_energy_final_over_max"] < 1e-2  # the deposit has come to rest
