"""Plain NumPy references of the generic engine's kernels, written with full matrices (no
component bookkeeping): the material laws :func:`fei_tensor_np` and :func:`ngf_tensor_np` and the
transfer :func:`p2g_np`.
tests/test_engine.py checks the compiled kernels against them."""

from __future__ import annotations

import numpy as np

from ..materials.params import DRIVER_A, DRIVER_B, DRIVER_C, DRIVER_P

_SYM = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))


def sym_to_mat(e: np.ndarray) -> np.ndarray:
    """(n, 6) components xx, yy, zz, xy, xz, yz → (n, 3, 3)."""
    m = np.zeros((e.shape[0], 3, 3))
    for c, (i, j) in enumerate(_SYM):
        m[:, i, j] = e[:, c]
        m[:, j, i] = e[:, c]
    return m


def mat_to_sym(m: np.ndarray) -> np.ndarray:
    return np.stack([m[:, i, j] for i, j in _SYM], axis=1)


def fei_tensor_np(mat: np.void, L: np.ndarray, e: np.ndarray, J: np.ndarray, phi: np.ndarray,
                  dt: float) -> dict[str, np.ndarray]:  # fmt: skip
    """Fei et al. 2016 for arrays of points: L (n, 3, 3), e (n, 6), J (n,), φ (n,).
    Returns the new strain and stress (n, 6) and p_e, γ̇, I, S, c, ν."""
    eye = np.eye(3)
    d = 0.5 * (L + np.swapaxes(L, 1, 2))
    w = 0.5 * (L - np.swapaxes(L, 1, 2))
    E = sym_to_mat(e)
    E = E + dt * (d + w @ E - E @ w)
    tr = lambda a: np.trace(a, axis1=1, axis2=2)[:, None, None]  # noqa: E731
    dp = d - tr(d) / 3.0 * eye
    gdot = np.sqrt(2.0 * np.einsum("nij,nij->n", dp, dp))
    E0 = E - tr(E) / 3.0 * eye
    I2 = 0.5 * np.einsum("nij,nij->n", E0, E0)
    I1 = -np.log(J)
    gas = I1 <= 0
    I1p = np.where(gas, 1.0, I1)
    cap = mat["capr"] * I1p
    s = np.where(I2 > cap**2, cap / np.sqrt(np.where(I2 > 0, I2, 1.0)), 1.0)
    E0 = E0 * s[:, None, None]
    I2 = np.minimum(I2, cap**2)
    A, C, rho_s = mat["a"], mat["c"], mat["rho_s"]
    rho = mat["f"] * rho_s / J
    sq = np.sqrt(I1p)
    pe = 2.5 * A * I1p**1.5 + 0.5 * C * I2 / sq
    dbar = phi * mat["ds"] + (1.0 - phi) * mat["dl"]
    a, b = mat["mu_a"] * mat["sdf"], mat["mu_b"]
    g = np.maximum(gdot, mat["gfloor"]) if b != 1.0 else np.ones_like(gdot)
    eta = a * dbar**b * rho_s ** (0.5 * b) * pe ** (1.0 - 0.5 * b) * g ** (b - 1.0)
    inertial = gdot * dbar / np.sqrt(pe / rho_s)
    c = np.sqrt((3.75 * A + 2.0 * C) * sq / rho)
    zeta = mat["zeta"] * rho * c * mat["h"]
    sig = (-pe[:, None, None] * eye + (C * sq)[:, None, None] * E0
           + 2.0 * eta[:, None, None] * dp + (zeta * tr(d)[:, 0, 0])[:, None, None] * eye)  # fmt: skip
    drv = int(mat["driver"])
    if drv == DRIVER_A:
        S = eta * gdot
    elif drv == DRIVER_B:
        S = mat["kappa_t"] * rho * (gdot * dbar) ** 2
    elif drv == DRIVER_P:
        S = pe.copy()
    else:
        S = -2.0 * eta * dp[:, 1, 1]
    S = S * mat["kappa"]
    nu = (eta + zeta) / rho
    enew = E0 - (I1 / 3.0)[:, None, None] * eye
    out = {"eps": mat_to_sym(enew), "sig": mat_to_sym(sig), "pe": pe, "gdot": gdot,
           "inertial": inertial, "S": S, "c": c, "nu": nu}  # fmt: skip
    for k, v in out.items():  # the gas state: no stress, the strain tracks the density
        if k == "gdot":
            continue
        v[gas] = 0.0
    out["eps"][gas, :3] = (-I1[gas] / 3.0)[:, None]
    return out


def ngf_tensor_np(mat: np.void, L: np.ndarray, e: np.ndarray, J: np.ndarray, phi: np.ndarray,
                  g: np.ndarray, dt: float) -> dict[str, np.ndarray]:  # fmt: skip
    """The fluidity flow rule of the nonlocal rheology for arrays of points, with full matrices:
    L (n, 3, 3), e (n, 6), J, φ, g (n,). The return factor f of ε⁰ ← f ε⁰_tr is found by
    bisection (``materials.ngf.return_factor_np``), independently of the kernel's Newton
    iteration. Returns the new strain and stress (n, 6) and p_e, γ̇, I, S, c, ν."""
    from ..materials.ngf import return_factor_np

    eye = np.eye(3)
    tr = lambda a: np.trace(a, axis1=1, axis2=2)[:, None, None]  # noqa: E731
    d = 0.5 * (L + np.swapaxes(L, 1, 2))
    w = 0.5 * (L - np.swapaxes(L, 1, 2))
    E = sym_to_mat(e)
    E = E + dt * (d + w @ E - E @ w)
    dp = d - tr(d) / 3.0 * eye
    gdot = np.sqrt(2.0 * np.einsum("nij,nij->n", dp, dp))
    E0 = E - tr(E) / 3.0 * eye
    I2 = 0.5 * np.einsum("nij,nij->n", E0, E0)
    I1 = -np.log(J)
    gas = I1 <= 0
    I1p = np.where(gas, 1.0, I1)
    A, C, rho_s = mat["a"], mat["c"], mat["rho_s"]
    sq = np.sqrt(I1p)
    a0 = 2.5 * A * I1p**1.5
    k = 0.5 * C * sq * dt * g
    lim = 4.0 * (a0 + k) * sq / C
    pull = np.where(I2 > lim, np.sqrt(lim / np.where(I2 > 0, I2, 1.0)), 1.0)
    I2 = np.minimum(I2, lim)
    f = return_factor_np(a0, 0.5 * C * I2 / sq, k)
    I2 = I2 * f**2
    cap = mat["capr"] * I1p
    f = f * pull * np.where(I2 > cap**2, cap / np.sqrt(np.where(I2 > 0, I2, 1.0)), 1.0)
    I2 = np.minimum(I2, cap**2)
    E0 = E0 * f[:, None, None]
    rho = mat["f"] * rho_s / J
    pe = 2.5 * A * I1p**1.5 + 0.5 * C * I2 / sq
    dbar = phi * mat["ds"] + (1.0 - phi) * mat["dl"]
    inertial = gdot * dbar / np.sqrt(pe / rho_s)
    c = np.sqrt((3.75 * A + 2.0 * C) * sq / rho)
    zeta = mat["zeta"] * rho * c * mat["h"]
    sig = (-pe[:, None, None] * eye + (C * sq)[:, None, None] * E0
           + (zeta * tr(d)[:, 0, 0])[:, None, None] * eye)  # fmt: skip
    drv = int(mat["driver"])
    if drv == DRIVER_A:
        S = mat["ngf_b"] * inertial * pe
    elif drv == DRIVER_B:
        S = mat["kappa_t"] * rho * (gdot * dbar) ** 2
    elif drv == DRIVER_C:
        S = np.zeros_like(pe)
    elif drv == DRIVER_P:
        S = pe.copy()
    else:
        S = mat["kappa_g"] * rho * (g * dbar) ** 2
    S = S * mat["kappa"]
    nu = zeta / rho
    enew = E0 - (I1 / 3.0)[:, None, None] * eye
    out = {"eps": mat_to_sym(enew), "sig": mat_to_sym(sig), "pe": pe, "gdot": gdot,
           "inertial": inertial, "S": S, "c": c, "nu": nu}  # fmt: skip
    for key, v in out.items():
        if key == "gdot":
            continue
        v[gas] = 0.0
    out["eps"][gas, :3] = (-I1[gas] / 3.0)[:, None]
    return out


def bspline2_1d(xi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Base node, weights (n, 3) and derivatives per grid unit (n, 3)."""
    base = np.floor(xi - 0.5).astype(np.int64)
    f = xi - base
    w = np.stack([0.5 * (1.5 - f) ** 2, 0.75 - (f - 1.0) ** 2, 0.5 * (f - 0.5) ** 2], axis=-1)
    dw = np.stack([f - 1.5, -2.0 * (f - 1.0), f - 0.5], axis=-1)
    return base, w, dw


def p2g_np(x, v, C, mass, vol, sig, h, origin, shape, periodic_x):
    """3-D P2G, point by point with full matrices: nodal mass (nx, ny, nz), momentum and force
    (nx, ny, nz, 3). ``C`` (n, 3, 3), ``sig`` (n, 3, 3)."""
    nx, ny, nz = shape
    m = np.zeros(shape)
    mom = np.zeros((*shape, 3))
    f = np.zeros((*shape, 3))
    xi = (x - np.asarray(origin)[None, :]) / h
    bases, ws, ds = zip(*(bspline2_1d(xi[:, a]) for a in range(3)), strict=True)
    for p in range(x.shape[0]):
        for a in range(3):
            i = bases[0][p] + a
            if periodic_x:
                i %= nx
            for b in range(3):
                j = bases[1][p] + b
                for c in range(3):
                    k = bases[2][p] + c
                    w = ws[0][p, a] * ws[1][p, b] * ws[2][p, c]
                    grad = np.array([ds[0][p, a] * ws[1][p, b] * ws[2][p, c],
                                     ws[0][p, a] * ds[1][p, b] * ws[2][p, c],
                                     ws[0][p, a] * ws[1][p, b] * ds[2][p, c]]) / h  # fmt: skip
                    node = np.asarray(origin) + h * np.array([bases[0][p] + a, j, k])
                    e = node - x[p]
                    m[i, j, k] += w * mass[p]
                    mom[i, j, k] += w * mass[p] * (v[p] + C[p] @ e)
                    f[i, j, k] -= vol[p] * sig[p] @ grad
    return m, mom, f


def smooth_dilatation_np(x, mass, L, J, h, origin, shape, periodic_x, dt):
    """3-D volumetric smoothing, point by point with full matrices: the nodal averages
    a_i = Σ_p w_ip m_p tr L_p / Σ_p w_ip m_p, tr L̄_p = Σ_i w_ip a_i / Σ_i w_ip (nodes with mass),
    L̄ = L + (tr L̄ − tr L)/3 I and J det(I + Δt L̄). ``L`` (n, 3, 3). Returns (L̄, J)."""
    m = np.zeros(shape)
    mt = np.zeros(shape)
    xi = (x - np.asarray(origin)[None, :]) / h
    bases, ws, _ = zip(*(bspline2_1d(xi[:, a]) for a in range(3)), strict=True)
    tr = np.trace(L, axis1=1, axis2=2)

    def stencil(p):
        for a in range(3):
            i = bases[0][p] + a
            if periodic_x:
                i %= shape[0]
            for b in range(3):
                for c in range(3):
                    yield (
                        (i, bases[1][p] + b, bases[2][p] + c),
                        ws[0][p, a] * ws[1][p, b] * ws[2][p, c],
                    )

    for p in range(x.shape[0]):
        for node, w in stencil(p):
            m[node] += w * mass[p]
            mt[node] += w * mass[p] * tr[p]
    Lbar = L.copy()
    Jn = np.empty_like(J)
    for p in range(x.shape[0]):
        num = wsum = 0.0
        for node, w in stencil(p):
            if m[node] > 0.0:
                num += w * mt[node] / m[node]
                wsum += w
        if wsum > 0.0:
            Lbar[p] += (num / wsum - tr[p]) / 3.0 * np.eye(3)
        Jn[p] = J[p] * np.linalg.det(np.eye(3) + dt * Lbar[p])
    return Lbar, Jn
