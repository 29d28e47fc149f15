"""Constitutive models: stress from (rate of deformation, state). No grid, no I/O.

Each model has a compiled per-point update with the contract of
:func:`segmpm.materials.fei2016.fei_update` and a NumPy reference with the suffix ``_np``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .._fmath import flog
from .elastic import elastic_update, elastic_update_np
from .fei2016 import fei_update_i1, fei_update_np, linear_in_I
from .ngf import ngf_update_i1, ngf_update_np
from .params import KIND_FEI2016, KIND_FEI2016_NGF, KIND_LINEAR_ELASTIC, M_KIND, pack_material

#: the material variants of the time loop: each compiles to a loop of its own (``update_stress``)
VAR_ELASTIC, VAR_FEI_LINEAR, VAR_FEI_POWER, VAR_NGF = range(4)


@njit(cache=True, error_model="numpy")
def material_variant(prm):
    """The variant of the record ``prm``: linear elastic, Fei 2016 with b = 1 (no powers, the
    loop vectorises) or with b ≠ 1, or the Jiang–Liu elasticity with the fluidity flow rule."""
    if prm[M_KIND] == KIND_FEI2016_NGF:
        return VAR_NGF
    if prm[M_KIND] != KIND_FEI2016:
        return VAR_ELASTIC
    return VAR_FEI_LINEAR if linear_in_I(prm) else VAR_FEI_POWER


@njit(cache=True, error_model="numpy", inline="always")
def material_update(prm, l00, l01, l10, l11, dt, exx, eyy, exy, ezz, J, phi, gf):
    """Dispatch on the model chosen at set-up (slot ``M_KIND``); ``gf`` the point's fluidity
    (used by the nonlocal variant only)."""
    return material_update_var(
        material_variant(prm), prm, l00, l01, l10, l11, dt, exx, eyy, exy, ezz, J, phi, gf
    )


@njit(cache=True, error_model="numpy", inline="always")
def material_update_var(var, prm, l00, l01, l10, l11, dt, exx, eyy, exy, ezz, J, phi, gf):
    """:func:`material_update` of the variant ``var`` (``VAR_*``). Called with a constant
    ``var``, the compiled code keeps only that branch, without calls for the linear elastic, the
    b = 1 and the nonlocal variants (I₁ = −ln J by :func:`segmpm._fmath.flog`), so that a loop
    over points vectorises."""
    if var == VAR_NGF:
        I1 = -flog(J)
        return ngf_update_i1(prm, l00, l01, l10, l11, dt, exx, eyy, exy, ezz, J, I1, phi, gf)
    if var == VAR_FEI_LINEAR:
        I1 = -flog(J)
        return fei_update_i1(prm, l00, l01, l10, l11, dt, exx, eyy, exy, ezz, J, I1, phi, True)
    if var == VAR_FEI_POWER:
        I1 = -flog(J)
        return fei_update_i1(prm, l00, l01, l10, l11, dt, exx, eyy, exy, ezz, J, I1, phi, False)
    return elastic_update(prm, l00, l01, l10, l11, dt, exx, eyy, exy, ezz, J, phi)


def material_update_np(prm, L, dt, eps, J, phi, gf=None):
    """NumPy reference dispatch (``gf``: the fluidity of the points, nonlocal variant)."""
    if prm[M_KIND] == KIND_FEI2016_NGF:
        return ngf_update_np(prm, L, dt, eps, J, phi, gf if gf is not None else np.zeros_like(J))
    if prm[M_KIND] == KIND_FEI2016:
        return fei_update_np(prm, L, dt, eps, J, phi)
    return elastic_update_np(prm, L, dt, eps, J, phi)


__all__ = [
    "KIND_LINEAR_ELASTIC",
    "KIND_FEI2016",
    "KIND_FEI2016_NGF",
    "KIND_LINEAR_ELASTIC",
    "material_update",
    "material_update_var",
    "material_variant",
    "VAR_ELASTIC",
    "VAR_FEI_LINEAR",
    "VAR_FEI_POWER",
    "VAR_NGF",
    "material_update_np",
    "pack_material",
]
