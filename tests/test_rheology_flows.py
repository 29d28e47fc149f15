"""Flows of the Fei et al. model against closed forms (docs/model.md §3).

Tolerances: the steady Bagnold surface speed within 2 % and the sidewall chute within 5 % (the
issue's), the profile shapes by RMS, and the stiffness scale by ≤ 1 %. The residual errors are
boundary-limited (first order in h at the no-slip base, docs/model.md), so the resolutions
below are chosen to keep them inside these tolerances.
"""

from __future__ import annotations

import math
from functools import cache

import numpy as np
import pytest
from conftest import make_sim

from segmpm.engine.records import XX, XY, YY

A_MU, QC, F, G, DBAR, W = 0.46, 0.38 * 2 * 0.95 / (1 + 0.95**2), 0.6, 9.81, 2.5e-3, 0.022


def bagnold(y, H, theta):
    """u(y) of the Bagnold layer with μ_eff = q_c + a I."""
    inert = (math.tan(math.radians(theta)) - QC) / A_MU
    k = 2 * inert / (3 * DBAR) * math.sqrt(F * G * math.cos(math.radians(theta)))
    return k * (H**1.5 - np.clip(H - y, 0, None) ** 1.5)


def sidewall(y, H, theta, mu_w):
    """u(y) of the sidewall-confined chute and the flowing depth ζ_f."""
    al = math.tan(math.radians(theta)) - QC
    be = mu_w / W
    zf = min(al / be, H)
    k = math.sqrt(F * G * math.cos(math.radians(theta))) / (A_MU * DBAR)
    z = np.minimum(np.clip(H - y, 0, None), zf)
    return k * ((2 / 3) * al * (zf**1.5 - z**1.5) - (2 / 5) * be * (zf**2.5 - z**2.5)), zf


@cache
def chute_run(theta, H, mu_w, scale, h, t_end):
    sim = make_sim([
        f"geometry.slope_deg={theta}", f"geometry.depth={H}", f"geometry.length={4 * h}",
        f"grid.cell_size={h}", f"boundary.sidewall_friction={mu_w}",
        f"material.stiffness_scale={scale}", "segregation.model='none'",
    ])  # fmt: skip
    sim.advance_to(t_end)
    st = sim.engine.points
    rows = np.unique(np.round(st.x[1], 9))
    u = np.array([st.v[0][np.abs(st.x[1] - r) < 1e-9].mean() for r in rows])
    return rows, u, sim


@pytest.mark.parametrize("theta, H", [(26.0, 0.006), (30.0, 0.008)])
def test_bagnold_steady_surface_velocity_and_shape(theta, H):
    # h = 0.5 mm: 12–16 cells over the depth. With image nodes at the base the error is second
    # order in h (+0.26 % / +0.12 % measured at h = 0.5 mm, +0.24 % / +0.10 % at 0.25 mm); without
    # them the one-sided wall stencil gave +2.9 % / +2.1 % (first order: +1.6 % / +1.1 % at 0.25 mm)
    rows, u, sim = chute_run(theta, H, 0.0, 1e-3, 5e-4, 0.6)
    th = bagnold(rows, H, theta)
    assert abs(u[-1] / th[-1] - 1) < 0.01, (u[-1], th[-1])
    assert np.sqrt(np.mean((u - th) ** 2)) / th[-1] < 0.01
    # the stress state: −σ_xy/σ_yy = tan θ in the interior, p linear in depth
    st = sim.engine.points
    mid = (st.x[1] > 0.2 * H) & (st.x[1] < 0.8 * H)
    ratio = np.mean(-st.sig[XY][mid] / st.sig[YY][mid])
    assert abs(ratio / math.tan(math.radians(theta)) - 1) < 0.01
    inert = (math.tan(math.radians(theta)) - QC) / A_MU
    assert abs(np.mean(st.diag[2][mid]) / inert - 1) < 0.03


@pytest.mark.parametrize("theta, mu_w", [(26.0, 0.3), (28.0, 0.4)])
def test_sidewall_chute_flowing_depth_surface_velocity_static_bed(theta, mu_w):
    H = 0.012
    rows, u, sim = chute_run(theta, H, mu_w, 1e-3, 5e-4, 0.8)
    th, zf = sidewall(rows, H, theta, mu_w)
    assert abs(u[-1] / th[-1] - 1) < 0.05, (u[-1], th[-1])

    def flowing_depth(uu):
        return H - rows[np.nonzero(uu > 0.02 * uu[-1])[0][0]]

    assert abs(flowing_depth(u) / flowing_depth(th) - 1) < 0.05
    assert np.sqrt(np.mean((u - th) ** 2)) / th[-1] < 0.03
    # a static bed below the flowing layer
    bed = rows < H - zf - 1.0e-3
    assert bed.sum() > 3
    assert np.max(np.abs(u[bed])) < 1e-3 * th[-1]


def test_stiffness_scale_does_not_change_the_flow():
    H, h = 0.006, 5e-4
    surf = {s: chute_run(26.0, H, 0.0, s, h, 0.45)[1][-1] for s in (1.0, 1e-2, 1e-3)}
    ref = surf[1.0]
    for v in surf.values():
        assert abs(v / ref - 1) < 0.01, surf
    side = {s: chute_run(26.0, 0.012, 0.3, s, h, 0.8)[1][-1] for s in (1e-2, 1e-3)}
    assert abs(side[1e-2] / side[1e-3] - 1) < 0.01, side


def test_oedometric_column_K0_stress_and_strain():
    """A column on a rigid base, periodic sides (no lateral strain), settles under gravity from
    half its geostatic compaction. σ_yy carries the weight above, K₀ = (2.5A − C/6)/(2.5A + 5C/6)
    = 0.767, and I₁ follows the oedometric law e = (−σ_yy/(2.5A + 5C/6))^{2/3} (closed forms:
    docs/model.md §3)."""
    H, L = 0.01, 0.002
    sim = make_sim([
        "geometry.slope_deg=0", f"geometry.depth={H}", f"geometry.length={L}",
        "boundary.sidewall_friction=0", "material.stiffness_scale=1e-3",
        "segregation.model='none'", "material.bulk_viscosity=0.5",
    ])  # fmt: skip
    st = sim.engine.points
    half = -0.5 * np.log(st.J)
    st.J[:] = np.exp(-half)
    st.eps[YY] *= 0.5
    sim.prime()  # σ and the diagnostics of the edited strain
    y0 = st.x[1].copy()
    sim.advance_to(0.25)
    assert np.max(np.abs(st.v)) < 1e-6  # static
    Aa, Cc = sim.engine.mat["a"][0], sim.engine.mat["c"][0]
    K0 = (2.5 * Aa - Cc / 6) / (2.5 * Aa + 5 * Cc / 6)
    assert abs(K0 - 0.767) < 5e-4
    inner = (y0 > 0.2 * H) & (y0 < 0.8 * H)
    np.testing.assert_allclose(st.sig[XX][inner] / st.sig[YY][inner], K0, rtol=2e-3)
    g = 9.81
    # σ_yy averaged over a cell (its two rows of points, which alternate by ±3 %, the known MPM
    # stress oscillation) carries the weight above
    rows = np.unique(np.round(st.x[1][inner], 9))
    rows = rows[: 2 * (len(rows) // 2)]
    syy = np.array([-st.sig[YY][np.abs(st.x[1] - r) < 1e-9].mean() for r in rows])
    above = np.array([st.mass[st.x[1] > r + 1e-9].sum() + 0.5 * st.mass[np.abs(st.x[1] - r) < 1e-9].sum()
                      for r in rows]) * g / L  # fmt: skip
    np.testing.assert_allclose(syy.reshape(-1, 2).mean(1), above.reshape(-1, 2).mean(1), rtol=0.01)
    e = (-st.sig[YY][inner] / (2.5 * Aa + 5 * Cc / 6)) ** (2 / 3)
    np.testing.assert_allclose(-np.log(st.J[inner]), e, rtol=0.01)
    # settlement of the top: (3/5) H Δe at the base to first order in e (docs/model.md §3). With
    # image nodes at the no-slip base it is within 1e-4; without them (first-order wall
    # kinematics, docs/model.md) it was +3 % at 20 cells over the depth
    top = y0 > y0.max() - 1e-9
    e_base = (F * 2650 * g * H / (2.5 * Aa + 5 * Cc / 6)) ** (2 / 3)
    expect = 0.6 * H * 0.5 * e_base
    settle = np.mean(y0[top] - st.x[1][top])
    assert abs(settle / expect - 1) < 0.01, (settle, expect)


def test_gas_transition_free_fall_and_recontact():
    """A dilating layer loses all stress (I₁ ≤ 0); it falls back and the stress returns on contact."""
    H = 0.004
    sim = make_sim([
        "geometry.slope_deg=0", f"geometry.depth={H}", "geometry.length=0.002",
        "boundary.sidewall_friction=0", "material.stiffness_scale=1e-3",
        "material.initial_state='stress_free'", "segregation.model='none'", "geometry.headroom=8",
        "material.bulk_viscosity=1.0",
        "boundary.base='slip'",
    ])  # fmt: skip
    st = sim.engine.points
    st.v[1] = 0.15 + 0.15 * st.x[1] / H  # launched and stretched: the layer expands and flies
    sim.prime()
    M = st.mass.sum()
    sim.advance_to(0.005)
    v1 = np.sum(st.mass * st.v[1]) / M
    sim.advance_to(0.01)
    assert np.all(st.J > 1.0) and np.min(st.x[1]) > 0.2e-3  # dilated and lifted off
    assert np.max(np.abs(st.sig)) == 0.0 and np.max(st.diag[0]) == 0.0
    # free flight of a stress-free body: the centre of mass accelerates at exactly −g
    v2 = np.sum(st.mass * st.v[1]) / M
    assert abs((v2 - v1) / 0.005 + 9.81) < 1e-9
    sim.advance_to(0.5)  # fallen back onto the base
    base = st.x[1] < 0.5e-3
    assert np.all(st.diag[0][base] > 0.0)  # contacts (stress) are back
    p_static = F * 2650 * 9.81 * H
    assert 0.3 * p_static < np.mean(st.diag[0][base]) < 3 * p_static


def test_seed_strip_length_does_not_change_the_profiles():
    """The default preset's 2-cell periodic strip is exact, not an approximation: the initial
    lattice is the same in every cell column and the layer is uniform along the slope, so the
    solution is invariant under a shift by one cell and a longer strip repeats it. The depth
    profiles of a 2-cell and a 7-cell strip of the coupled seed case (flow + segregation) agree to
    round-off after 0.05 s (about 4000 steps of the whole start-up transient)."""
    profiles = []
    for cells in (2, 7):
        sim = make_sim(
            [f"geometry.length={cells * 0.0005}", "time.end=0.05", "segregation.dt=1e-4"]
        )
        sim.advance_to(0.05)
        assert sim.engine.n == cells * 2 * 149
        profiles.append(sim.profiles())
    a, b = profiles
    for key in ("velocity_x", "phi_small", "pressure", "shear_stress", "solid_fraction"):
        scale = np.nanmax(np.abs(b[key]))
        np.testing.assert_allclose(a[key], b[key], rtol=0, atol=1e-9 * scale, err_msg=key)
    assert np.nanmax(b["velocity_x"]) > 1e-3  # it flowed
    assert np.nanstd(b["phi_small"]) > 0  # and segregated


def test_closed_form_module_matches_the_test_oracle():
    """segmpm.analysis.closed_form (used by validation/chute_closed_form.py) gives the same
    profiles as this file's independent transcription of the closed forms (docs/model.md §3)."""
    from segmpm.analysis.closed_form import bagnold_velocity, sidewall_velocity
    from segmpm.config import load_config

    for theta, H, mu_w in ((26.0, 0.006, 0.3), (31.0, 0.02, 0.15)):
        cfg = load_config(preset="chute_seed", overrides=[f"geometry.slope_deg={theta}", f"geometry.depth={H}",
                                     f"boundary.sidewall_friction={mu_w}"])  # fmt: skip
        y = np.linspace(0, H, 50)
        np.testing.assert_allclose(bagnold_velocity(cfg, y), bagnold(y, H, theta), rtol=1e-12)
        u, zf = sidewall_velocity(cfg, y)
        u_ref, zf_ref = sidewall(y, H, theta, mu_w)
        np.testing.assert_allclose(u, u_ref, rtol=1e-12, atol=1e-15)
        assert zf == zf_ref
