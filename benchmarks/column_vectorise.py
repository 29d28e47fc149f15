"""The column model's element pass inline in a serial loop against the same pass in a one-block
parallel region (``prange(1)``), one thread: why ``column.advance_column`` wraps its passes in
such regions (docs/performance.md, "The nonlocal default and the column model").

    NUMBA_NUM_THREADS=1 python benchmarks/column_vectorise.py [--repeats 20000]
"""

from __future__ import annotations

import argparse
import time

from numba import njit, prange

from segmpm.column import _elements, build_column
from segmpm.config import load_config
from segmpm.materials import VAR_FEI_LINEAR, VAR_NGF
from segmpm.mpm.step import prime


def _make(var: int, parallel: bool):
    if parallel:

        @njit(parallel=True, fastmath={"contract"})
        def run(n, dt, nodes, v, J, eps, sig, phi, gf, diag, s_int, g_int, mp):
            for _ in range(n):
                for _b in prange(1):
                    _elements(var, dt, nodes, v, J, eps, sig, phi, gf, diag, s_int, g_int, mp)

    else:

        @njit(fastmath={"contract"})
        def run(n, dt, nodes, v, J, eps, sig, phi, gf, diag, s_int, g_int, mp):
            for _ in range(n):
                _elements(var, dt, nodes, v, J, eps, sig, phi, gf, diag, s_int, g_int, mp)

    return run


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=20000)
    a = ap.parse_args()
    for preset, var, name in (("chute_seed", VAR_FEI_LINEAR, "local"),
                              ("chute_nonlocal", VAR_NGF, "nonlocal")):  # fmt: skip
        cfg = load_config(preset=preset, overrides=["scenario.solver='column'"])
        st = build_column(cfg)
        prime(st.J, st.eps, st.sig, st.phi, st.gf, st.diag, st.mp, st.v)
        args = (1e-9, st.nodes, st.v, st.J, st.eps, st.sig, st.phi, st.gf, st.diag, st.s_int,
                st.g_int, st.mp)  # fmt: skip
        out = []
        for parallel in (False, True, False, True):
            f = _make(var, parallel)
            f(1, *args)
            t0 = time.perf_counter()
            f(a.repeats, *args)
            ns = (time.perf_counter() - t0) / a.repeats / st.n * 1e9
            out.append(f"{'region' if parallel else 'inline'} {ns:.1f}")
        print(f"{name} element pass, ns per element ({st.n} elements): " + ", ".join(out))


if __name__ == "__main__":
    main()
