"""The engine of a given dimension: the template :mod:`segmpm.engine.kernels` written out with
``D`` set, and imported.

Numba's ``cache=True`` keys a compiled function by its source file, and does not cache closures
built by a factory. So the specialisations are real files: ``kernels_d2.py`` and ``kernels_d3.py``
under ``<kernel cache>/generated/``. The kernel cache directory is itself keyed by a hash of every
source file of the package (:mod:`segmpm._cache`), the template included, so a generated file
can never be stale; it is written only when its text changes (atomically: another process may be
importing it), so that its cached machine code stays valid. Only the dimension that a run uses
is generated, imported and compiled.
"""

from __future__ import annotations

import importlib.util
import os
import sys
import tempfile
from pathlib import Path
from types import ModuleType

from .._cache import KERNEL_CACHE

TEMPLATE = Path(__file__).with_name("kernels.py")
#: the template's line that the generator replaces
DIM_LINE = "D = 2\n"

_loaded: dict[int, ModuleType] = {}


def render(dim: int) -> str:
    """The source of the ``dim``-dimensional kernels."""
    if dim not in (2, 3):
        raise ValueError(f"dimension must be 2 or 3, got {dim}")
    text = TEMPLATE.read_text()
    if text.count(DIM_LINE) != 1:
        raise RuntimeError(f"{TEMPLATE} must contain the line {DIM_LINE!r} exactly once")
    header = (
        f"# GENERATED from segmpm/engine/kernels.py for D = {dim} by segmpm.engine.codegen;"
        " do not edit.\n"
    )
    return header + text.replace(DIM_LINE, f"D = {dim}\n")


def _write_if_changed(path: Path, text: str) -> None:
    try:
        if path.read_text() == text:
            return
    except OSError:
        pass
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def generated_dir() -> Path:
    """Where the generated sources live (inside the keyed kernel cache)."""
    return KERNEL_CACHE / "generated"


def kernels(dim: int) -> ModuleType:
    """The compiled-on-first-call kernels of dimension ``dim`` (2 or 3), generated if needed."""
    if dim in _loaded:
        return _loaded[dim]
    text = render(dim)
    path = generated_dir() / f"kernels_d{dim}.py"
    try:
        _write_if_changed(path, text)
    except OSError:
        # an unwritable cache: a private temporary copy (compiled anew in each process)
        path = Path(tempfile.mkdtemp(prefix="segmpm-gen-")) / f"kernels_d{dim}.py"
        path.write_text(text)
    name = f"segmpm._generated.kernels_d{dim}"
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    _loaded[dim] = mod
    return mod
