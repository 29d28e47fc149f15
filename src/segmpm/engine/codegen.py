"""The engine of a given dimension and law: the template :mod:`segmpm.engine.kernels` written out
with ``D`` and ``LAW`` set, and imported.

Numba's ``cache=True`` keys a compiled function by its source file, and does not cache closures
built by a factory. So the specialisations are real files under ``<kernel cache>/generated/``:

* ``kernels_d2.py`` and ``kernels_d3.py``: the template up to its line ``STEP_SECTION = True``
  (P2G, grid update, G2P, the laws, the fluidity and the concentration step), with ``D`` set;
* ``kernels_d2_law1.py`` …: the rest of the template (the material pass ``update_stress``,
  ``prime`` and the time loop ``advance``) with ``LAW`` set, executed in a namespace that holds
  the names of the dimension's file. So a run compiles the time loop of its own law only, and the
  kernels they share are compiled and cached once.
 The kernel cache directory is itself keyed by a hash of every
source file of the package (:mod:`segmpm._cache`), the template included, so a generated file
can never be stale; it is written only when its text changes (atomically: another process may be
importing it), so that its cached machine code stays valid. Only the dimension that a run uses
is generated, imported and compiled, and of it only the law that a run uses.
"""

from __future__ import annotations

import importlib.util
import os
import shutil
import sys
import tempfile
from pathlib import Path
from types import ModuleType

from .._cache import KERNEL_CACHE

TEMPLATE = Path(__file__).with_name("kernels.py")
#: the template's lines that the generator replaces or splits at
DIM_LINE = "D = 2\n"
STEP_LINE = "STEP_SECTION = True\n"
LAW_LINE = "LAW = LAW_FEI\n"
#: the laws (``LAW_*`` of the template, the ``VAR_*`` of :mod:`segmpm.materials`)
LAWS = range(4)

_loaded: dict[tuple[int, int | None], ModuleType] = {}


def _once(text: str, line: str) -> int:
    if text.count(line) != 1:
        raise RuntimeError(f"{TEMPLATE} must contain the line {line!r} exactly once")
    return text.index(line)


def render(dim: int, law: int | None = None) -> str:
    """The source of the ``dim``-dimensional kernels (``law`` None), or of the step section of
    the law ``law`` (0 … 3: elastic, Fei with b = 1, Fei with b ≠ 1, nonlocal)."""
    if dim not in (2, 3):
        raise ValueError(f"dimension must be 2 or 3, got {dim}")
    if law is not None and law not in LAWS:
        raise ValueError(f"law must be one of {list(LAWS)}, got {law}")
    text = TEMPLATE.read_text()
    _once(text, DIM_LINE)
    split = _once(text, STEP_LINE)
    head, step = text[:split], text[split:]
    if law is None:
        header = (
            f"# GENERATED from segmpm/engine/kernels.py for D = {dim} by segmpm.engine.codegen;"
            " do not edit.\n"
        )
        return header + head.replace(DIM_LINE, f"D = {dim}\n")
    _once(step, LAW_LINE)
    header = (
        f"# GENERATED from the step section of segmpm/engine/kernels.py for D = {dim}, LAW ="
        f" {law} by segmpm.engine.codegen; do not edit. It runs in the namespace of"
        f" kernels_d{dim}.py.\n"
    )
    return header + step.replace(LAW_LINE, f"LAW = {law}\n")


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


def file_name(dim: int, law: int | None = None) -> str:
    """The generated file's name: ``kernels_d2.py``, ``kernels_d2_law1.py`` …"""
    return f"kernels_d{dim}.py" if law is None else f"kernels_d{dim}_law{law}.py"


def kernels(dim: int, law: int | None = None) -> ModuleType:
    """The compiled-on-first-call kernels of dimension ``dim`` (2 or 3), generated if needed.

    With ``law`` (``law_of(mat)`` of the run's record; see :func:`for_material`) the module also
    has the material pass, ``prime`` and the time loop ``advance`` of that law; without, only the
    kernels the laws share."""
    key = (dim, law)
    if key in _loaded:
        return _loaded[key]
    text = render(dim, law)
    base = None if law is None else kernels(dim)
    fname = file_name(dim, law)
    path = generated_dir() / fname
    try:
        _write_if_changed(path, text)
    except OSError:
        # an unwritable cache: a private temporary copy (compiled anew in each process); if
        # that cannot be written either, the error reaches the caller and no copy is left
        tmp = Path(tempfile.mkdtemp(prefix="segmpm-gen-"))
        path = tmp / fname
        try:
            path.write_text(text)
        except OSError:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
    name = f"segmpm._generated.{fname[:-3]}"
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    if base is not None:  # the step section runs in the namespace of the dimension's kernels
        mod.__dict__.update({k: v for k, v in vars(base).items() if not k.startswith("__")})
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    _loaded[key] = mod
    return mod


def for_material(dim: int, mat: object) -> ModuleType:
    """The kernels of dimension ``dim`` with the step of the law of the record ``mat``."""
    return kernels(dim, int(kernels(dim).law_of(mat)))
