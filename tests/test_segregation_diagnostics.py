"""Segregation diagnostics: small-grain volume, centroids, segregation index."""

from __future__ import annotations

import numpy as np
import pytest

from segmpm.segregation.diagnostics import (
    segregation_index,
    small_grain_volume,
    species_centroids,
)
from segmpm.segregation.reference import strip_layout


@pytest.mark.parametrize("phi0", [0.5, 0.3])
def test_index_of_mixed_and_fully_segregated_layers(phi0: float) -> None:
    depth = 0.01
    px, py, vol0 = strip_layout(0.004, depth, 0.25e-3)
    mixed = np.full(px.size, phi0)
    assert segregation_index(py, vol0, mixed) == pytest.approx(0.0, abs=1e-12)
    assert small_grain_volume(vol0, mixed) == pytest.approx(phi0 * 0.004 * depth, rel=1e-12)
    normal = (py < phi0 * depth).astype(float)  # small grains at the bottom
    y_s, y_l = species_centroids(py, vol0, normal)
    assert y_s == pytest.approx(0.5 * phi0 * depth, rel=1e-9)
    assert y_l == pytest.approx(0.5 * (1.0 + phi0) * depth, rel=1e-9)
    assert segregation_index(py, vol0, normal) == pytest.approx(1.0, abs=1e-3)
    assert segregation_index(py, vol0, normal, depth=depth) == pytest.approx(1.0, abs=1e-12)
    inverse = (py > (1.0 - phi0) * depth).astype(float)
    assert segregation_index(py, vol0, inverse) == pytest.approx(-1.0, abs=1e-3)


def test_centroids_of_a_missing_species_are_nan() -> None:
    py = np.linspace(0.0, 1.0, 11)
    vol0 = np.ones_like(py)
    y_s, y_l = species_centroids(py, vol0, np.zeros_like(py))
    assert np.isnan(y_s) and y_l == pytest.approx(0.5)
