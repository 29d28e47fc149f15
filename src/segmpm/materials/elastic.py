"""Linear (hypo-)elastic material for verification (vibrating bar, free fall, momentum tests).

σ = λ tr ε 1 + 2 μ ε with a Jaumann update of the small strain ε; plane strain (ε_zz = 0).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .._fmath import fsqrt
from .fei2016 import deviatoric_rate, jaumann_predictor, jaumann_predictor_np
from .params import M_F, M_LAMBDA, M_MU, M_RHO_S


@njit(cache=True, error_model="numpy", inline="always")
def elastic_update(prm, l00, l01, l10, l11, dt, exx, eyy, exy, ezz, J, phi):
    """Stress update of one point; same contract as :func:`segmpm.materials.fei2016.fei_update`."""
    lam = prm[M_LAMBDA]
    mu = prm[M_MU]
    rho = prm[M_F] * prm[M_RHO_S] / J
    exx, eyy, exy, ezz = jaumann_predictor(exx, eyy, exy, ezz, l00, l01, l10, l11, dt)
    tr = exx + eyy + ezz
    sxx = lam * tr + 2.0 * mu * exx
    syy = lam * tr + 2.0 * mu * eyy
    sxy = 2.0 * mu * exy
    szz = lam * tr + 2.0 * mu * ezz
    p = -(sxx + syy + szz) / 3.0
    gdot = deviatoric_rate(l00, l01, l10, l11)[5]
    c = fsqrt((lam + 2.0 * mu) / rho)
    return exx, eyy, exy, ezz, sxx, syy, sxy, szz, p, gdot, 0.0, 0.0, c, 0.0


def elastic_update_np(prm, L, dt, eps, J, phi):
    """NumPy reference of :func:`elastic_update` (arrays of points)."""
    L = np.asarray(L, dtype=np.float64)
    lam, mu = prm[M_LAMBDA], prm[M_MU]
    rho = prm[M_F] * prm[M_RHO_S] / J
    d, E2 = jaumann_predictor_np(L, dt, eps)
    ezz = np.asarray(eps)[:, 3]
    tr = E2[:, 0, 0] + E2[:, 1, 1] + ezz
    sig = np.stack(
        [
            lam * tr + 2 * mu * E2[:, 0, 0],
            lam * tr + 2 * mu * E2[:, 1, 1],
            2 * mu * E2[:, 0, 1],
            lam * tr + 2 * mu * ezz,
        ],
        axis=1,
    )
    eps_new = np.stack([E2[:, 0, 0], E2[:, 1, 1], E2[:, 0, 1], ezz], axis=1)
    p = -(sig[:, 0] + sig[:, 1] + sig[:, 3]) / 3.0
    D3 = np.zeros((len(J), 3, 3))
    D3[:, :2, :2] = d
    Dp = D3 - np.trace(D3, axis1=1, axis2=2)[:, None, None] / 3.0 * np.eye(3)
    gdot = np.sqrt(2.0 * np.einsum("nij,nij->n", Dp, Dp))
    c = np.sqrt((lam + 2 * mu) / rho)
    z = np.zeros_like(J)
    return eps_new, sig, p, gdot, z, z, c, z
