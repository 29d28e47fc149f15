"""Constitutive models: their parameter record (``params.pack_material``) and the plane-strain
NumPy references of the point updates (suffix ``_np``), which the engine's compiled laws
(``engine/kernels.py``: ``fei_tensor``, ``ngf_tensor``, the elastic law, in full tensor form)
are tested against. No grid, no I/O. The local relaxation of the fluidity
(``ngf.relax_logistic``) and the return factor of the flow rule (``ngf.return_factor``) are
compiled here and called by the engine as they are.
"""

from __future__ import annotations

import numpy as np

from .elastic import elastic_update_np
from .fei2016 import fei_update_np
from .ngf import ngf_update_np
from .params import KIND_FEI2016, KIND_FEI2016_NGF, KIND_LINEAR_ELASTIC, M_KIND, pack_material

#: the material laws of the time loop (``engine.kernels.LAW_*``): each compiles to a loop of
#: its own (``update_stress``)
VAR_ELASTIC, VAR_FEI_LINEAR, VAR_FEI_POWER, VAR_NGF = range(4)


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
    "VAR_ELASTIC",
    "VAR_FEI_LINEAR",
    "VAR_FEI_POWER",
    "VAR_NGF",
    "material_update_np",
    "pack_material",
]
