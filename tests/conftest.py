"""Shared helpers of the test suite."""

from __future__ import annotations

import os

import numpy as np
import pytest

os.environ.setdefault("MPLBACKEND", "Agg")

import numba  # noqa: E402

from segmpm.config import load_config  # noqa: E402
from segmpm.simulation import Simulation  # noqa: E402

# The suite runs the compiled loop on one thread: numba's parallel regions spin-wait, and on a
# shared 2-core machine a second thread that loses its core slows every step by an order of
# magnitude. Results do not depend on the thread count (test_reliability checks 1 vs 2 threads,
# which stays possible because NUMBA_NUM_THREADS is left as it is). Subprocesses get SUBPROCESS_ENV.
numba.set_num_threads(1)
SUBPROCESS_ENV = {**os.environ, "NUMBA_NUM_THREADS": "1"}


def make_sim(overrides: list[str], out_dir=None, preset: str = "chute_seed") -> Simulation:
    """A quiet simulation from a built-in preset (the seed's local model unless told) plus
    overrides. The suite names its preset rather than relying on the built-in default, so the
    physics tests do not move when the default does."""
    base = ["output.progress=false", "output.fields=false", "output.figures=false"]
    return Simulation(load_config(preset=preset, overrides=base + overrides), out_dir=out_dir)


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)
