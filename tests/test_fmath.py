"""The vectorisable primitives of the compiled kernels against the C library: ``fsqrt`` is the
IEEE square root (correctly rounded, so equal to ``math.sqrt`` bit for bit) and ``flog`` is within
one unit in the last place of ``math.log``, with the same special values."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from segmpm._fmath import flog, fsqrt


@njit(cache=True, error_model="numpy")
def _apply(a):
    """``flog`` and ``fsqrt`` of every element."""
    lg = np.empty_like(a)
    sq = np.empty_like(a)
    for i in range(a.shape[0]):
        lg[i] = flog(a[i])
        sq[i] = fsqrt(a[i])
    return lg, sq


def _flog(a):
    return _apply(a)[0]


def _fsqrt(a):
    return _apply(a)[1]


def _samples(rng):
    return np.concatenate([
        rng.uniform(0.5, 2.0, 200_000),  # around the reduction interval [√½, √2)
        1.0 + rng.normal(scale=1e-3, size=200_000),  # volume ratios of a granular flow
        1.0 + rng.normal(scale=1e-9, size=20_000),  # ln x ≈ x − 1: relative accuracy near 1
        np.exp(rng.uniform(-700.0, 700.0, 200_000)),  # the whole normal range
        rng.uniform(0.0, 2.2250738585072014e-308, 20_000),  # subnormal
        np.nextafter(np.sqrt(0.5), [0.0, 1.0]), np.nextafter(np.sqrt(2.0), [0.0, 2.0]),
        [5e-324, 2.2250738585072014e-308, 0.5, 1.0, 2.0, 1.7976931348623157e308],
    ])  # fmt: skip


def test_flog_within_one_ulp_of_the_library(rng):
    x = _samples(rng)
    ref = np.array([math.log(v) for v in x])
    got = _flog(x)
    exact = ref == got
    ulps = np.abs(got - ref) / np.spacing(np.abs(ref))
    assert np.max(np.where(exact, 0.0, ulps)) <= 1.0
    assert np.mean(exact) > 0.9  # mostly the correctly rounded value itself
    assert _flog(np.array([1.0]))[0] == 0.0


def test_flog_special_values():
    got = _flog(np.array([0.0, -0.0, -1.0, -np.inf, np.inf, np.nan]))
    assert got[0] == -np.inf and got[1] == -np.inf
    assert np.isnan(got[2]) and np.isnan(got[3]) and np.isnan(got[5])
    assert got[4] == np.inf


def test_fsqrt_is_the_ieee_square_root(rng):
    x = np.concatenate([_samples(rng), [0.0, -0.0, np.inf]])
    np.testing.assert_array_equal(_fsqrt(x), np.array([math.sqrt(v) for v in x]))
    assert np.isnan(_fsqrt(np.array([-1.0, np.nan]))).all()
