"""Time each kernel of the compiled step separately (docs/performance.md, "Where the time goes").

Builds the seed chute with about N points (as ``segmpm bench``), runs 60 steps, then times the
kernels on that state, interleaved over 25 rounds, and prints the best time of each in ns per
point. G2P and the material law are timed on a restored copy of the state. Usage:

    python benchmarks/kernels.py [N] [THREADS]
"""

from __future__ import annotations

import sys
import time

import numba
import numpy as np

from segmpm.bench import _config_for
from segmpm.mpm import step as stepmod
from segmpm.mpm import transfer
from segmpm.mpm.params import S_DT
from segmpm.segregation.grid import concentration_step
from segmpm.simulation import Simulation


def main() -> int:
    n_req = int(sys.argv[1]) if len(sys.argv) > 1 else 32000
    nt = int(sys.argv[2]) if len(sys.argv) > 2 else 1
    sim = Simulation(_config_for(n_req))
    sim.threads = nt
    sim.advance(1.0, 60)
    numba.set_num_threads(nt)  # for the kernels called directly below
    st, w = sim.state, sim.state.work
    x, v, C, J, eps, sig, diag = st.x, st.v, st.C, st.J, st.eps, st.sig, st.diag
    dt = float(st.sc[S_DT])  # the last stable step
    bounds = np.zeros(numba.get_num_threads() + 1, dtype=np.int64)
    moving = (x, v, C, J, eps, sig, diag, st.s_int, st.g_int)
    snap = [a.copy() for a in moving]

    def restore():
        for a, b in zip(moving, snap, strict=True):
            a[:] = b

    kernels = {
        "strip sort": lambda: transfer.sort_into_strips(
            x[1], st.gp, w["strip_start"], w["cursor"], w["order"]
        ),
        "P2G": lambda: transfer.p2g(
            x,
            v,
            C,
            st.mass,
            st.vol0,
            J,
            sig,
            diag[0],
            st.gp,
            w["grid"],
            w["strip_start"],
            w["order"],
            bounds,
            True,
        ),  # fmt: skip
        "grid update": lambda: transfer.grid_update(st.gp, w["grid"], w["gv"], dt, 1.0, True),
        "(restore)": restore,
        "G2P": lambda: (
            restore(),
            stepmod.update_points(
                x,
                v,
                C,
                J,
                st.gp,
                w["gv"],
                dt,
                w["flags"],
                w["cursor"],
                w["strip_start"].shape[0] - 1,
                w["lg"],
            ),
        ),  # fmt: skip
        "(restore 2)": restore,
        "material law + check": lambda: (
            restore(),
            stepmod.update_stress(
                x,
                v,
                J,
                eps,
                sig,
                st.phi,
                st.gf,
                diag,
                st.s_int,
                st.g_int,
                st.mp,
                dt,
                w["flags"],
                w["lg"],
                False,
                numba.get_num_threads(),
            ),
        ),  # fmt: skip
        "check (MUSL path only)": lambda: stepmod._check(x, v, J, sig, diag, w["flags"]),
        "concentration step (per call)": lambda: concentration_step(
            x[0],
            x[1],
            st.vol0,
            st.phi.copy(),
            st.s_int.copy(),
            st.g_int.copy(),
            1e-3,
            st.cg,
            st.seg_prm,
            st.seg_work,
        ),
    }
    best = dict.fromkeys(kernels, np.inf)
    for f in kernels.values():
        f()
    for _ in range(25):
        for name, f in kernels.items():
            t0 = time.perf_counter()
            for _ in range(4):
                f()
            best[name] = min(best[name], (time.perf_counter() - t0) / 4 / st.n * 1e9)
    best["G2P"] -= best.pop("(restore)")
    best["material law + check"] -= best.pop("(restore 2)")
    print(f"N = {st.n}, threads = {numba.get_num_threads()}: ns per point")
    for name, t in best.items():
        print(f"  {name:32s} {t:8.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
