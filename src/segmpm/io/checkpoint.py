"""Checkpoints: everything a run needs to continue bit-for-bit (just another output writer).

``checkpoint/state.npz`` holds the material-point arrays, the scalar state (time, step counter,
time-step controller) and the concentration-grid state. It is written to a temporary file and
renamed, so the previous checkpoint survives until the new one is complete.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from .atomic import write_with

FORMAT_VERSION = 1


def save_checkpoint(path: str | Path, arrays: dict[str, np.ndarray], meta: dict[str, Any]) -> None:
    """Atomically write a checkpoint with ``arrays`` and JSON-serialisable ``meta``."""
    payload = {k: np.asarray(v) for k, v in arrays.items()}
    payload["__meta__"] = np.frombuffer(
        json.dumps({"format": FORMAT_VERSION, **meta}).encode(), dtype=np.uint8
    )

    def _write(tmp: Path) -> None:
        with open(tmp, "wb") as fh:
            np.savez(fh, **payload)

    write_with(path, _write)


def load_checkpoint(path: str | Path) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
    """Read a checkpoint written by :func:`save_checkpoint`."""
    with np.load(path, allow_pickle=False) as z:
        arrays = {k: z[k].copy() for k in z.files if k != "__meta__"}
        meta = json.loads(bytes(z["__meta__"]).decode())
    if meta.get("format") != FORMAT_VERSION:
        raise ValueError(
            f"checkpoint {path} has format {meta.get('format')}, expected {FORMAT_VERSION}"
        )
    return arrays, meta
