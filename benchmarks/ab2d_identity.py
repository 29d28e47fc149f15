"""2-D identity and throughput of a checkout against another, on a preset (default chute_seed,
the seed's local model; chute_nonlocal the nonlocal default), one thread: one run per call, so
that calls can be interleaved A/B/A/B.

    git worktree add /tmp/wt_pre 19ee395      # the commit before the generic engine
    for r in 1 2 3 4 5; do
      NUMBA_NUM_THREADS=1 python benchmarks/ab2d_identity.py $PWD/src head 1.0 [PRESET]
      NUMBA_NUM_THREADS=1 python benchmarks/ab2d_identity.py /tmp/wt_pre/src pre 1.0 [PRESET]
    done
    python -c "import numpy as np; a, b = np.load('/tmp/ab/state_pre.npz'), np.load('/tmp/ab/state_head.npz'); print(all(np.array_equal(a[k], b[k]) for k in a.files))"

(With a PRESET other than chute_seed the files are ``state_<tag>_<PRESET>.npz``.) Each call
prints a JSON line (steps, loop seconds excluding the compile, and the process CPU seconds
of the same stretch, which leave out the time a shared host steals) and saves the final state to
/tmp/ab/state_<tag>.npz. Both checkouts may share one ``SEGMPM_CACHE_DIR``: the kernel cache is
keyed by a hash of the sources.
"""

import json
import os
import sys
import time

import numpy as np

src = sys.argv[1]
tag = sys.argv[2]
end = float(sys.argv[3])
preset = sys.argv[4] if len(sys.argv) > 4 else "chute_seed"
suffix = "" if preset == "chute_seed" else f"_{preset}"
sys.path.insert(0, src)
import segmpm  # noqa: E402
from segmpm.config import load_config  # noqa: E402
from segmpm.simulation import Simulation  # noqa: E402

os.makedirs("/tmp/ab", exist_ok=True)
assert segmpm.__file__.startswith(src), segmpm.__file__
cfg = load_config(
    None, [f"time.end={end}", "output.progress=false", "grid.threads=1"], preset=preset
)
sim = Simulation(cfg, f"/tmp/ab/out_{tag}{suffix}")
sim.advance_to(1e-4)  # compile
w0 = sim.wall_time
t0 = time.perf_counter()
c0 = time.process_time()
sim.advance_to(end)
cpu = time.process_time() - c0
el = time.perf_counter() - t0
# the default engine's points (generic since 2026-12-07, σ stored xx, yy, zz, xy) or the former
# engine's state (σ stored xx, yy, xy, zz): saved in the former order
generic = hasattr(sim, "engine")
st = sim.engine.points if generic else sim.state
sig = st.sig[[0, 1, 3, 2]] if generic else st.sig
np.savez(f"/tmp/ab/state_{tag}{suffix}.npz", x=st.x, v=st.v, sig=sig, phi=st.phi)
print(
    json.dumps(
        {
            "tag": tag,
            "preset": preset,
            "steps": sim.steps,
            "loop_s": sim.wall_time - w0,
            "wall_s": el,
            "cpu_s": cpu,
            "n": sim.engine.n if generic else sim.state.n,
        }
    )
)
