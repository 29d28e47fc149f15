"""Linear (hypo-)elastic material for verification (vibrating bar, free fall, momentum tests).

σ = λ tr ε 1 + 2 μ ε with a Jaumann update of the small strain ε; plane strain (ε_zz = 0).
"""

from __future__ import annotations

import numpy as np

from .fei2016 import jaumann_predictor_np
from .params import M_F, M_LAMBDA, M_MU, M_RHO_S


def elastic_update_np(prm, L, dt, eps, J, phi):
    """NumPy reference of the linear elastic point update (plane strain, arrays of points)."""
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
