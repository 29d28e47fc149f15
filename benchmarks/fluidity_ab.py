"""The fluidity update alone at the default run's 596 points, on this checkout (the engine's
``fluidity_step``) or on the commit before the generic engine (its ``mpm.fluidity``), on the
state of the nonlocal default after 0.2 s: µs per call, best and median of 5 blocks of 20 000
calls, one thread. Interleave the two checkouts:

    for r in 1 2; do for t in head pre; do s=$PWD/src; [ $t = pre ] && s=/tmp/wt_pre/src
      NUMBA_NUM_THREADS=1 PYTHONPATH=$s python benchmarks/fluidity_ab.py $s $t; done; done
"""

from __future__ import annotations

import json
import statistics
import sys
import time


def main(src: str, tag: str, reps: int = 20000) -> dict:
    sys.path.insert(0, src)
    from segmpm.config import load_config
    from segmpm.simulation import Simulation

    cfg = load_config(None, ["output.progress=false", "grid.threads=1"], preset="chute_nonlocal")
    sim = Simulation(cfg, f"/tmp/ab/flu_{tag}")
    sim.advance_to(0.2)
    if tag == "pre":  # the former plane-strain engine's update
        from segmpm.mpm.fluidity import fluidity_step

        st = sim.state
        gf = st.gf
        nflu = int(st.sc[8])

        def call() -> None:
            fluidity_step(st.x, st.mass, st.phi, st.sig, st.diag[0], st.gf, st.gp, st.mp,
                          st.work["fw"], 2e-4)  # fmt: skip
    else:
        from segmpm.engine.codegen import kernels

        e, k = sim.engine, kernels(2)
        gf = e.points.gf
        nflu = int(sim.clock["nflu"])

        def call() -> None:
            k.fluidity_step(e.points, e.grid, e.prm, e.mat, 2e-4)

    gf0 = gf.copy()
    call()  # compile or load
    blocks = []
    for _ in range(5):
        gf[:] = gf0
        t0 = time.perf_counter()
        for _ in range(reps):
            call()
        blocks.append((time.perf_counter() - t0) / reps * 1e6)
    return {"tag": tag, "us_per_call": min(blocks), "median": statistics.median(blocks),
            "steps": sim.steps, "fluidity_updates": nflu}  # fmt: skip


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1], sys.argv[2])))
