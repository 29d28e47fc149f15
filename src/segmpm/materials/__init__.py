"""Constitutive models: stress from (rate of deformation, state). No grid, no I/O.

Each model has a compiled per-point update with the contract of
:func:`segmpm.materials.fei2016.fei_update` and a NumPy reference with the suffix ``_np``.
"""

from __future__ import annotations

import math

from numba import njit

from .elastic import elastic_update_i1, elastic_update_np
from .fei2016 import fei_update_i1, fei_update_np
from .params import KIND_FEI2016, KIND_LINEAR_ELASTIC, M_KIND, pack_material


@njit(cache=True, error_model="numpy", inline="always")
def material_update(prm, l00, l01, l10, l11, dt, exx, eyy, exy, ezz, J, phi):
    """Dispatch on the model chosen at set-up (slot ``M_KIND``)."""
    I1 = -math.log(J) if prm[M_KIND] == KIND_FEI2016 else 0.0
    return material_update_i1(prm, l00, l01, l10, l11, dt, exx, eyy, exy, ezz, J, I1, phi)


@njit(cache=True, error_model="numpy", inline="always")
def material_update_i1(prm, l00, l01, l10, l11, dt, exx, eyy, exy, ezz, J, I1, phi):
    """:func:`material_update` with I₁ = −ln J given (the time loop's form; the linear elastic
    model does not use it)."""
    if prm[M_KIND] == KIND_FEI2016:
        return fei_update_i1(prm, l00, l01, l10, l11, dt, exx, eyy, exy, ezz, J, I1, phi)
    return elastic_update_i1(prm, l00, l01, l10, l11, dt, exx, eyy, exy, ezz, J, I1, phi)


def material_update_np(prm, L, dt, eps, J, phi):
    """NumPy reference dispatch."""
    if prm[M_KIND] == KIND_FEI2016:
        return fei_update_np(prm, L, dt, eps, J, phi)
    return elastic_update_np(prm, L, dt, eps, J, phi)


__all__ = [
    "KIND_FEI2016",
    "KIND_LINEAR_ELASTIC",
    "material_update",
    "material_update_i1",
    "material_update_np",
    "pack_material",
]
