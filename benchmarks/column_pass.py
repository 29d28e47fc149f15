"""Where the generic engine's column spends its material pass: the pass of
``engine.kernels.update_stress`` taken apart on the seed column (149 elements, one thread),
each variant in a one-block parallel region called ``--repeats`` times from compiled code,
printed as ns per element:

    NUMBA_NUM_THREADS=1 python benchmarks/column_pass.py [--repeats 20000]

law: the law alone with L read from ``P.lg``; law-const: the same with L's two zero entries
(∂u/∂x, ∂v/∂x) passed as constants; block: ``_stress_block`` (the law, the stores, the
diagnostics buffer); block+reduce: with ``_reduce_block``; update_stress: the MPM's whole pass
(blocks in parallel, parallel reductions); column_stress: the column's pass (one block, the
reduction after the region), which ``advance_column`` calls.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from numba import njit, prange

from segmpm.config import load_config
from segmpm.engine.codegen import for_material
from segmpm.simulation import Simulation


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=20000)
    a = ap.parse_args()
    over = ["scenario.solver='column'", "grid.engine='generic'", "output.fields=false",
            "output.progress=false"]  # fmt: skip
    sim = Simulation(load_config(preset="chute_seed", overrides=over))
    sim.threads = 1
    sim.advance_to(0.02)
    e = sim.engine
    K = for_material(e.dim, e.mat)
    law, LAW, _sym, _mat = K.law, K.LAW, K._sym, K._mat
    block, reduce, update, B_ROWS = K._stress_block, K._reduce_block, K.update_stress, K.B_ROWS
    column = K.column_stress

    def variant(kind: str):
        @njit(error_model="numpy", parallel=True, fastmath={"contract"})
        def run(P, mat, dt, reps):
            n = P.J.shape[0]
            lg = P.lg
            acc = 0.0
            buf = np.empty((B_ROWS, n))
            for _ in range(reps):
                if kind == "update_stress":
                    acc += update(P, mat, dt, False, 1)[2]
                    continue
                if kind == "column_stress":
                    acc += column(P, mat, dt, False, buf)[2]
                    continue
                for _b in prange(1):
                    if kind == "block" or kind == "block+reduce":
                        block(LAW, 0, n, buf, P, mat, dt)
                        if kind == "block+reduce":
                            reduce(0, n, n, buf, P.diag, False)
                    else:
                        for u in range(np.uint64(n)):
                            if kind == "law-const":
                                L = (0.0, lg[1, u], 0.0, 0.0, lg[3, u], 0.0, 0.0, 0.0, 0.0)
                            else:
                                L = _mat(lg, u)
                            r = law(LAW, mat, L, _sym(P.eps, u), P.J[u], P.phi[u], P.gf[u], dt)
                            P.diag[1, u] = r[6] + r[13] + r[16] + r[0] + r[3]
            return acc

        return run

    dt = float(e.clock[0]["dt"])
    kinds = ("law", "law-const", "block", "block+reduce", "update_stress", "column_stress")
    runs = {k: variant(k) for k in kinds}
    for f in runs.values():
        f(e.points, e.mat, dt, 10)
    for rnd in range(2):
        for k in kinds:
            t0 = time.perf_counter()
            runs[k](e.points, e.mat, dt, a.repeats)
            ns = (time.perf_counter() - t0) / a.repeats / e.n * 1e9
            print(f"round {rnd}: {k:14s} {ns:6.1f} ns per element", flush=True)


if __name__ == "__main__":
    main()
