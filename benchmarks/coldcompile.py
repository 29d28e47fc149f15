"""Cold compile time of one bench variant: build the case and take one step with an empty kernel
cache (set ``SEGMPM_CACHE_DIR`` to a new directory), printing the set-up (which compiles the
initial stress pass) and first-call seconds as JSON. Run two source trees side by side (one with
``PYTHONPATH=<other tree>/src``) so that both see the same load:

    SEGMPM_CACHE_DIR=$(mktemp -d) python benchmarks/coldcompile.py local

(The variant was ``generic-local`` until the former plane-strain engine was removed on
2026-12-07; ``local`` is now the same case on the one engine.)
"""

from __future__ import annotations

import json
import sys
import time

t0 = time.perf_counter()
import segmpm  # noqa: E402
from segmpm.bench import _config_for  # noqa: E402
from segmpm.simulation import Simulation  # noqa: E402


def main(variant: str) -> dict:
    sim = Simulation(_config_for(600, variant))
    sim.threads = 1
    t1 = time.perf_counter()
    sim.advance(1.0, 1)
    t2 = time.perf_counter()
    return {"src": segmpm.__file__, "variant": variant, "import_setup_s": round(t1 - t0, 1),
            "first_call_s": round(t2 - t1, 1)}  # fmt: skip


if __name__ == "__main__":
    print(json.dumps(main(sys.argv[1] if len(sys.argv) > 1 else "local")))
