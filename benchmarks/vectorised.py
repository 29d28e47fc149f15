"""Is the material pass's block loop vectorised? Compile one block of it fresh and look for packed
(SIMD) square roots in the machine code, for the production 2-D pass (``mpm.step``) and the
dimension-generic one (``engine``), per law.

A call, a power or an early return in a law leaves the loop scalar and the pass 2-4x slower
(docs/performance.md). This is a property of the generated code, not of the physics, and what LLVM
sees depends on the state of the kernel cache: a callee loaded from the cache is linked as object
code and cannot be inlined, so the check runs each case in its own process with an empty
``SEGMPM_CACHE_DIR``. It used to be a test; as a test it depended on which kernels an earlier test
had compiled in the same process (docs/performance.md, "The vectorisation check").

    python benchmarks/vectorised.py                  # every case, one process each
    python benchmarks/vectorised.py generic 3 nonlocal  # one case in this process
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import tempfile
import time

CASES = [
    ("production", 2, "fei-b1"),
    ("production", 2, "nonlocal"),
    ("generic", 2, "fei-b1"),
    ("generic", 2, "nonlocal"),
    ("generic", 3, "fei-b1"),
    ("generic", 3, "nonlocal"),
]

NONLOCAL = ["material.rheology='nonlocal'", "material.q_phi=0.6",
            "segregation.model='hill_tan_fluidity'"]  # fmt: skip


def _config(dim: int, law: str):
    from segmpm.config import load_config

    over = ["output.fields=false", "output.figures=false", "output.progress=false",
            f"geometry.dimension={dim}"]  # fmt: skip
    if dim == 3:
        over += ["grid.cell_size=0.001", "geometry.length=0.002", "segregation.model='none'"]
    if law == "nonlocal":
        over += NONLOCAL
    return load_config(None, over, preset="chute_seed")


def _generic_asm(dim: int, law: str) -> str:
    import numba
    import numpy as np

    from segmpm.engine.codegen import kernels
    from segmpm.engine.setup import build

    k = kernels(dim)
    st = build(_config(dim, law), dim)
    which = k.law_of(st.mat)
    P = st.points

    @numba.njit(error_model="numpy", parallel=True, fastmath={"contract"})
    def one_block(P, mat, dt):
        buf = np.empty((k.B_ROWS, k.BLOCK))
        for _ in numba.prange(1):
            k._stress_block(which, 0, min(k.BLOCK, P.J.shape[0]), buf, P, mat, dt)
        return buf

    one_block(P, st.mat, 1e-5)
    return one_block.inspect_asm(one_block.signatures[0])


def _production_asm(law: str) -> str:
    import numba
    import numpy as np

    from segmpm.materials import material_variant
    from segmpm.mpm import step as S
    from segmpm.scenarios import build

    st = build(_config(2, law))
    var = int(material_variant(st.mp))
    w = st.work

    @numba.njit(error_model="numpy", parallel=True, fastmath={"contract"})
    def one_block(v, J, eps, sig, phi, gf, diag, s_int, g_int, mp, dt, flags, lg):
        buf = np.empty((S.B_ROWS, S.BLOCK))
        for _ in numba.prange(1):
            S._stress_block(var, 0, min(S.BLOCK, J.shape[0]), buf, v, J, eps, sig, phi, gf,
                            diag, s_int, g_int, mp, dt, flags, lg)  # fmt: skip
        return buf

    one_block(st.v, st.J, st.eps, st.sig, st.phi, st.gf, st.diag, st.s_int, st.g_int, st.mp,
              1e-5, w["flags"], w["lg"])  # fmt: skip
    return one_block.inspect_asm(one_block.signatures[0])


def one(engine: str, dim: int, law: str) -> dict:
    t0 = time.perf_counter()
    asm = _production_asm(law) if engine == "production" else _generic_asm(dim, law)
    return {"engine": engine, "dim": dim, "law": law,
            "packed_sqrt": len(re.findall(r"\bv?sqrtpd\b", asm)),
            "scalar_sqrt": len(re.findall(r"\bv?sqrtsd\b", asm)),
            "vectorised": bool(re.search(r"\bv?sqrtpd\b", asm)),
            "compile_s": round(time.perf_counter() - t0, 1)}  # fmt: skip


def main(argv: list[str]) -> int:
    if argv:
        print(json.dumps(one(argv[0], int(argv[1]), argv[2])), flush=True)
        return 0
    rows = []
    for engine, dim, law in CASES:
        with tempfile.TemporaryDirectory() as cache:
            env = dict(os.environ, SEGMPM_CACHE_DIR=cache, NUMBA_NUM_THREADS="1")
            out = subprocess.run([sys.executable, __file__, engine, str(dim), law], env=env,
                                 capture_output=True, text=True, check=True)  # fmt: skip
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
        print(json.dumps(rows[-1]), flush=True)
    return 0 if all(r["vectorised"] for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
