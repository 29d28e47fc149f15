"""Atomic file writes: write to a temporary file in the same folder, fsync, then rename.

Every output of a run goes through :func:`atomic_path`, so a reader (or a run that resumes) sees
either the previous complete file or the new complete file, never a half-written one. A write
that fails for any OS reason (a full disk, ``EFBIG`` past a file-size limit, an I/O error, a
permission problem) removes its temporary file and raises :class:`OutputWriteError`, which names
the output and the cause. The file gets the mode a plain ``open()`` would give it (0o666 minus the
umask), not the 0o600 of :func:`tempfile.mkstemp`.
"""

from __future__ import annotations

import contextlib
import errno as _errno
import json
import os
import tempfile
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any


class OutputWriteError(OSError):
    """An output file could not be written; ``path`` is the output, ``cause`` the OS error.

    ``errno`` and ``strerror`` are those of the cause (``errno`` is None when the writer raised
    an OSError without one)."""

    def __init__(self, path: str | Path, cause: BaseException):
        code = getattr(cause, "errno", None)
        reason = getattr(cause, "strerror", None) or str(cause) or type(cause).__name__
        super().__init__(code, reason)
        self.path = Path(path)
        self.filename = str(path)
        self.cause = cause

    @property
    def code_name(self) -> str | None:
        """Symbolic name of the errno (``ENOSPC``, ``EFBIG``, …), or None."""
        return _errno.errorcode.get(self.errno) if isinstance(self.errno, int) else None

    def __str__(self) -> str:
        name = self.code_name
        return f"cannot write {self.path}: {self.strerror}" + (f" ({name})" if name else "")

    def __reduce__(self):  # picklable (dask returns exceptions from workers)
        return (_rebuild_output_error, (str(self.path), self.errno, self.strerror))


def _rebuild_output_error(path: str, code: int | None, reason: str) -> OutputWriteError:
    return OutputWriteError(path, OSError(code, reason) if code is not None else OSError(reason))


_UMASK_LOCK = threading.Lock()


def current_umask() -> int:
    """The process's umask (read from /proc where possible: ``os.umask`` can only be read by
    setting it, which is done under a lock)."""
    try:
        with open("/proc/self/status", encoding="ascii", errors="replace") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except (OSError, ValueError, IndexError):
        pass
    with _UMASK_LOCK:
        mask = os.umask(0o022)
        os.umask(mask)
    return mask


def file_mode() -> int:
    """The mode of a new regular file: 0o666 minus the umask."""
    return 0o666 & ~current_umask()


def remove_quietly(path: str | Path | None) -> None:
    """Remove ``path`` if it exists; errors are ignored (used to clean up temporary files)."""
    if path is None:
        return
    with contextlib.suppress(OSError):
        os.unlink(path)


def _commit(tmp: Path, path: Path) -> None:
    """Flush ``tmp`` to disk, give it the umask's mode and rename it over ``path``.

    (A module-level function, so that the tests can inject a failure at the N-th write.)"""
    with open(tmp, "rb+") as fh:
        os.fsync(fh.fileno())
    os.chmod(tmp, file_mode())
    os.replace(tmp, path)


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """Yield a temporary path next to ``path``; on success it replaces ``path`` atomically.

    On any error the temporary file is removed and ``path`` is left as it was; an OSError of the
    writer, of the fsync or of the rename is raised as :class:`OutputWriteError`. (A crash, e.g.
    SIGKILL, before the rename leaves at most a stray ``.NAME.*.tmp`` file, which readers ignore
    and the next run into the folder removes.)
    """
    path = Path(path)
    tmp_path: Path | None = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
        tmp_path = Path(tmp)
        os.close(fd)
    except OSError as err:
        remove_quietly(tmp_path)
        raise OutputWriteError(path, err) from err
    try:
        yield tmp_path
        _commit(tmp_path, path)
    except OutputWriteError:
        raise
    except OSError as err:
        raise OutputWriteError(path, err) from err
    finally:
        if tmp_path.exists():
            remove_quietly(tmp_path)


def write_text(path: str | Path, text: str) -> None:
    """Atomically write a text file."""
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def write_json(path: str | Path, data: Any) -> None:
    """Atomically write a JSON file (indented, keys in insertion order)."""
    write_text(path, json.dumps(data, indent=2, allow_nan=True) + "\n")


def write_with(path: str | Path, writer: Callable[[Path], None]) -> None:
    """Atomically write ``path`` with ``writer(tmp_path)``."""
    with atomic_path(path) as tmp:
        writer(tmp)
