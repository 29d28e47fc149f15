"""Throughput suite: `python benchmarks/run_bench.py` (same as `segmpm bench --json ...`).

Writes benchmarks/results/bench-<date>.json with particle-steps per second of the full coupled
step on the seed chute at N ≈ 8k, 32k and 128k points with 1 and 2 threads.
"""

from __future__ import annotations

import datetime
import pathlib
import sys

from segmpm.bench import run_bench

if __name__ == "__main__":
    out = pathlib.Path(__file__).parent / "results"
    out.mkdir(exist_ok=True)
    stamp = datetime.date.today().isoformat()
    sys.exit(run_bench([8000, 32000, 128000], [1, 2], 400, str(out / f"bench-{stamp}.json")))
