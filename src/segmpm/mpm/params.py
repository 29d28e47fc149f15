"""The codes shared with the engine (boundary kinds ``BC_*``, transfers ``TRANSFER_*``, loop
status ``ST_*``) and the records of the plane-strain NumPy references: the grid record ``gp``
(grid, boundaries, gravity, time-step control; slots ``G_*``) and the scalar state ``sc``
(``S_*``), one float64 array each. The engine's own records are named (segmpm.engine.records).
"""

from __future__ import annotations

BC_OPEN = 0
BC_NOSLIP = 1
BC_SLIP = 2
BC_FRICTION = 3
BC_CODES = {"open": BC_OPEN, "noslip": BC_NOSLIP, "slip": BC_SLIP, "friction": BC_FRICTION}

TRANSFER_APIC = 0
TRANSFER_FLIP = 1  # MUSL with a FLIP/PIC blend
TRANSFER_AFLIP = 2  # APIC affine transfer with a FLIP velocity update (Fei et al. 2021)

(
    G_X0,  # x of node (0, ·), m
    G_Y0,  # y of node (·, 0), m
    G_H,  # cell size h, m
    G_NX,  # nodes in x (periodic: L_x / h)
    G_NY,  # nodes in y
    G_PERIODIC,  # 1 if x is periodic
    G_LX,  # periodic length, m
    G_BASE_KIND,  # BC_* of the plane y = G_BASE_Y (nodes at and below it)
    G_BASE_Y,
    G_BASE_MU,
    G_XLO_KIND,  # BC_* of the plane x = G_XLO (nodes at and left of it), non-periodic only
    G_XLO,
    G_XHI_KIND,
    G_XHI,
    G_WALL_MU,
    G_GX,  # gravity in the slope frame, m/s²
    G_GY,
    G_SIDEWALL,  # 2 μ_w K_w / W, 1/m (0 disables the sidewall force)
    G_RAMP,  # ramp time of tangential gravity and sidewall friction, s
    G_CFL,
    G_DTMAX,
    G_DTMIN,
    G_TRANSFER,  # TRANSFER_*
    G_FLIP,  # FLIP fraction (TRANSFER_FLIP)
    G_IMAGES,  # 1: image (mirror) nodes behind no-slip walls that lie on a node plane
    G_VISC,  # viscous number: Δt ≤ G_VISC h²/(2 ν_max)
    G_CFLOOR,  # floor on the wave speed of the time step, m/s (the loaded material's c)
    G_SW_SLOW,  # 2 μ_w0 K_w / W: the sidewall factor at vanishing speed, 1/m
    G_SW_SPEED,  # u_w of μ_w(u) = μ_w0 + (μ_w − μ_w0) u/(u + u_w), m/s (0: constant μ_w)
    G_NSLOTS,
) = range(30)

# scalar state carried between chunks (float64 array)
(
    S_TIME,  # simulated time t, s
    S_STEP,  # steps taken
    S_TSEG,  # time accumulated towards the next concentration step, s
    S_SMAX,  # max over points of c + |v| after the last step, m/s
    S_NUMAX,  # max kinematic viscosity after the last step, m²/s
    S_DT,  # last time step, s
    S_NSEG,  # concentration steps taken
    S_TFLU,  # time accumulated towards the next fluidity update (nonlocal rheology), s
    S_NFLU,  # fluidity updates taken
    S_NSLOTS,
) = range(10)

# status returned by advance
ST_OK = 0
ST_NONFINITE = 1
ST_LEFT_GRID = 2
ST_DT_COLLAPSE = 3
STATUS_TEXT = {
    ST_OK: "ok",
    ST_NONFINITE: "non-finite state",
    ST_LEFT_GRID: "material point left the grid",
    ST_DT_COLLAPSE: "time step collapsed",
}
