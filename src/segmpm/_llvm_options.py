"""LLVM options for segmpm's compiled kernels, set when the time loop's module is imported (before
any kernel compiles; Numba compiles on the first call).

``-vectorize-memory-check-threshold``: the material pass (``update_stress`` of engine/kernels.py) reads and
writes some twenty rows of the point arrays. LLVM cannot prove that rows of one array and distinct
arrays do not overlap, so it vectorises such a loop behind run-time overlap checks, one pair of
address comparisons per pair of accessed ranges and per block of points, and gives up above 128
checks (the default). The pass needs about 190; the threshold is raised to 1024. This changes
which loops are vectorised, never a result: a loop whose ranges overlap at run time takes its
scalar version. The option is process-wide (it applies to every Numba function compiled
afterwards, also outside segmpm) and only loosens a cost limit.
"""

from __future__ import annotations

import llvmlite.binding as llvm

#: run-time pointer checks LLVM's loop vectoriser may emit for one loop (LLVM's default: 128)
VECTORIZE_MEMORY_CHECK_THRESHOLD = 1024

llvm.set_option("segmpm", f"-vectorize-memory-check-threshold={VECTORIZE_MEMORY_CHECK_THRESHOLD}")
