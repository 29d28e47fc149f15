"""Shared helpers of the test suite."""

from __future__ import annotations

import os

import numpy as np
import pytest

os.environ.setdefault("MPLBACKEND", "Agg")

from segmpm.config import load_config  # noqa: E402
from segmpm.simulation import Simulation  # noqa: E402


def make_sim(overrides: list[str], out_dir=None) -> Simulation:
    """A quiet simulation from the built-in default plus overrides."""
    base = ["output.progress=false", "output.fields=false", "output.figures=false"]
    return Simulation(load_config(overrides=base + overrides), out_dir=out_dir)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)
