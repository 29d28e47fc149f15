"""The kernel cache cannot go stale (segmpm._cache): Numba keys its own cache by the file that
defines a kernel, while segmpm's kernels inline functions of other modules. The engine's
fluidity update (generated from ``engine/kernels.py``) inlines ``relax_logistic`` of
``materials/ngf.py``; editing ngf.py alone in a copy of the package must change what the cached
``fluidity_step`` computes.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import segmpm
from segmpm._cache import source_hash

SCRIPT = r"""
import json, sys
import numpy as np
import segmpm
from segmpm._cache import KERNEL_CACHE
from segmpm.config import load_config
from segmpm.engine.codegen import kernels
from segmpm.engine.setup import build

assert segmpm.__file__.startswith(sys.argv[1]), segmpm.__file__
cfg = load_config(preset="chute_seed", overrides=["material.rheology='nonlocal'", "material.q_phi=0.75",
                             "segregation.model='none'", "geometry.length=0.001",
                             "grid.cell_size=5e-4", "geometry.depth=0.01"])
st = build(cfg, 2)
P = st.points
zeta = 0.01 - P.x[1]
p = 0.6 * 2650 * 9.81 * np.cos(np.radians(26.0)) * zeta
P.diag[0] = p
P.sig[:] = 0.0
P.sig[0] = P.sig[1] = P.sig[2] = -p
P.sig[3] = 0.45 * p
P.gf[:] = 5.0
kernels(2).fluidity_step(P, st.grid, st.prm, st.mat, 2.5e-4)
print(json.dumps({"gf": P.gf.tolist(), "cache": str(KERNEL_CACHE)}))
"""

EDIT = """

_relax_logistic_before_the_edit = relax_logistic


@njit(cache=True, error_model="numpy", inline="always")
def relax_logistic(g, mu, p, dbar, dt, rho_s, mu_s, t0, b, p_floor):  # noqa: F811 - the edit
    return 0.5 * _relax_logistic_before_the_edit(g, mu, p, dbar, dt, rho_s, mu_s, t0, b, p_floor)
"""


def _run(pkg_root: Path, cache: Path) -> dict:
    env = {**os.environ, "PYTHONPATH": str(pkg_root), "SEGMPM_CACHE_DIR": str(cache)}
    r = subprocess.run([sys.executable, "-c", SCRIPT, str(pkg_root)], env=env,
                       capture_output=True, text=True, timeout=900)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_an_edited_inlined_kernel_is_not_run_from_a_stale_cache(tmp_path):
    pkg_root = tmp_path / "pkg"
    src = Path(segmpm.__file__).resolve().parent
    # copy2 keeps the modification times: the kernel files look unchanged to Numba's own cache index
    shutil.copytree(src, pkg_root / "segmpm", ignore=shutil.ignore_patterns("__pycache__"))
    cache = tmp_path / "cache"
    before = _run(pkg_root, cache)
    again = _run(pkg_root, cache)  # the same sources: loaded from the same cache directory
    assert again["cache"] == before["cache"] and again["gf"] == before["gf"]
    hash_before = source_hash(pkg_root / "segmpm")
    ngf = pkg_root / "segmpm" / "materials" / "ngf.py"
    ngf.write_text(ngf.read_text() + EDIT)
    assert source_hash(pkg_root / "segmpm") != hash_before
    after = _run(pkg_root, cache)
    assert after["cache"] != before["cache"]
    g0, g1 = before["gf"], after["gf"]
    moved = [i for i, g in enumerate(g0) if g > 0.0]
    assert moved, "the check needs points with fluidity"
    for i in moved:  # the edit halves the local relaxation's result at every point
        assert abs(g1[i] - 0.5 * g0[i]) <= 1e-12 * g0[i], (i, g0[i], g1[i])
