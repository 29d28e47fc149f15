"""Where Numba caches segmpm's compiled kernels: a directory keyed by a hash of the package's
sources, so that a cached kernel can never be stale.

Numba keys its on-disk cache by the file that defines a function (its path and modification time)
and does not look at the functions it calls: the time loop in ``mpm/step.py`` inlines the
material laws of ``materials/*.py``, so editing a material law alone left the old machine code in
use (an edited law could silently run stale). Here every ``cache=True`` kernel of segmpm is cached
under ``<cache root>/kernels-<hash>``, where the hash covers the text of every ``.py`` file of the
package, the Numba, llvmlite, NumPy and Python versions and the CPU name: any edit selects a new,
empty directory. The cache root is ``$SEGMPM_CACHE_DIR`` if set, else ``$XDG_CACHE_HOME/segmpm``
(default ``~/.cache/segmpm``). This must run before the first kernel is defined (the package
imports it first).
"""

from __future__ import annotations

import hashlib
import os
import platform
import sys
from pathlib import Path

_PKG = Path(__file__).resolve().parent


def source_hash(root: Path = _PKG) -> str:
    """Hash of every ``.py`` file under ``root`` (paths and contents) and of the toolchain."""
    import llvmlite
    import numba
    import numpy

    h = hashlib.sha256()
    for p in sorted(root.rglob("*.py")):
        h.update(str(p.relative_to(root)).encode())
        h.update(b"\0")
        h.update(p.read_bytes())
        h.update(b"\0")
    for v in (numba.__version__, llvmlite.__version__, numpy.__version__, sys.version,
              platform.machine(), platform.processor()):  # fmt: skip
        h.update(str(v).encode())
    try:
        import llvmlite.binding as llvm

        h.update(llvm.get_host_cpu_name().encode())
    except Exception:  # noqa: BLE001 - the CPU name only refines the key
        pass
    return h.hexdigest()[:16]


def cache_root() -> Path:
    """The directory under which the keyed kernel caches live."""
    env = os.environ.get("SEGMPM_CACHE_DIR")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "segmpm"


#: keyed cache directories kept besides the one in use (the most recently used ones)
KEEP = 4


def _prune(root: Path, current: Path) -> None:
    """Remove all but the ``KEEP`` most recently used ``kernels-*`` directories (a developer's
    edits each make one); failures are ignored (another process may be using or removing one)."""
    import shutil

    try:
        dirs = [p for p in root.glob("kernels-*") if p.is_dir() and p != current]
        dirs.sort(key=lambda p: p.stat().st_mtime, reverse=True)
    except OSError:
        return
    for p in dirs[KEEP:]:
        shutil.rmtree(p, ignore_errors=True)


def configure() -> Path:
    """Point Numba's cache at ``cache_root()/kernels-<source_hash()>``; returns that directory."""
    import numba

    root = cache_root()
    d = root / f"kernels-{source_hash()}"
    try:
        d.mkdir(parents=True, exist_ok=True)
        os.utime(d)  # most recently used
    except OSError:
        # an unwritable cache root: fall back to Numba's own locations (the cache stays correct
        # for the kernels' own files, as before)
        return d
    numba.config.CACHE_DIR = str(d)
    _prune(root, d)
    return d


KERNEL_CACHE = configure()
