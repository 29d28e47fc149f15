"""Generic / production cost ratios of a ``segmpm bench --json`` run of the former A/B variants
(``generic-*``, removed with the plane-strain engine on 2026-12-07), per case: it reads the
committed result files of that A/B.

Each ``generic-X`` variant is divided by ``X`` round by round (the rounds interleave the
variants, so a ratio within a round shares the machine's state of that moment); prints the
median of those ratios, the ratio of the medians, the ratio of the best blocks and the
inter-quartile range of the per-round ratios.

    python benchmarks/ab_ratios.py benchmarks/results/engine2d-ab-2026-12-06e.json
"""

from __future__ import annotations

import json
import sys

import numpy as np


def ratios(path: str) -> list[str]:
    """One line per generic variant and case of the bench result file ``path``."""
    with open(path) as f:
        d = json.load(f)
    blocks = {(r["variant"], r["n_points"], r["threads"]): np.array(r["block_wall_s"])
              for r in d["results"]}  # fmt: skip
    lines = []
    for (v, n, t), b in sorted(blocks.items()):
        if not v.startswith("generic-") or (v[8:], n, t) not in blocks:
            continue
        a = blocks[(v[8:], n, t)]
        q = b / a
        lines.append(
            f"{v:17s} {n:6d} {t}  median ratio {np.median(q):.3f}  ratio of medians "
            f"{np.median(b) / np.median(a):.3f}  min-ratio {b.min() / a.min():.3f}  "
            f"IQR {np.percentile(q, 25):.3f}-{np.percentile(q, 75):.3f}"
        )
    return lines


if __name__ == "__main__":
    for path in sys.argv[1:]:
        print("\n".join(ratios(path)))
