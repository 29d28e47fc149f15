"""The output directory of a run: checks before the run, the lock, and segmpm's own files.

* :func:`prepare_out_dir` creates OUT and checks that files can be created in it, raising
  :class:`OutDirError` (exit 2) naming the path and the cause before anything runs.
* :class:`OutLock` holds ``OUT/.segmpm.lock`` for the duration of a run: an OS lock
  (``fcntl.flock``, released by the kernel on any exit, SIGKILL included) where the filesystem
  supports it, else (``ENOLCK``/``EOPNOTSUPP``, some NFS and Lustre mounts) a lock file created
  exclusively, holding host, PID and start time, that counts as stale when it names this host and
  a process that no longer exists. A second run into a locked OUT gets :class:`LockedError`
  naming the holder's host and PID.
* :func:`own_files` lists the files of OUT that segmpm writes (``profiles.nc``, ``run.json``,
  ``config.toml``, ``compare.json``, ``checkpoint/``, ``fields/particles*.vtu`` and
  ``particles.pvd``, ``figures/profiles.png`` and ``compare.png``, and stray temporary files of
  the atomic writer); :func:`foreign_files` everything else; :func:`remove_own_files` is what
  ``--overwrite`` does, so that ``--out .`` never removes a user's file.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import socket
import tempfile
import time
from pathlib import Path
from typing import Any

from ..config import Config, ConfigError

try:  # not on Windows: there the lock file alone is used
    import fcntl
except ImportError:  # pragma: no cover
    fcntl = None  # type: ignore[assignment]

LOCK_NAME = ".segmpm.lock"

#: files segmpm writes at the top of OUT
TOP_FILES = ("profiles.nc", "run.json", "config.toml", "compare.json")
#: files segmpm writes in the sub-folders of OUT (regular expressions of the name)
SUB_FILES = {
    "checkpoint": (r"state\.npz",),
    "fields": (r"particles_\d{4,}\.vtu", r"particles\.pvd"),
    "figures": (r"profiles\.png", r"compare\.png"),
}
# a temporary file of io.atomic (".NAME.XXXXXXXX.tmp", ".NAME.XXXXXXXX.tmp.evtk.vtu" of the VTK
# writer) for one of the names above, or the ".vtk.XXXXXXXX.vtu" of earlier versions
_TMP = r"\.(?:{names})\.[^/]+\.tmp(?:\.evtk\.vtu)?"
_OLD_VTK_TMP = r"\.vtk\.[^/]+(?:\.vtu)?"


def _own_name(folder: str, name: str) -> bool:
    names = TOP_FILES if folder == "" else SUB_FILES.get(folder, ())
    if folder == "":
        plain = "|".join(re.escape(n) for n in names)
    else:
        plain = "|".join(names)
    if re.fullmatch(f"(?:{plain})", name):
        return True
    if re.fullmatch(_TMP.format(names=plain), name):
        return True
    if folder == "" and re.fullmatch(r"\.segmpm-probe\.[^/]+\.tmp", name):  # prepare_out_dir's
        return True
    return folder == "fields" and re.fullmatch(_OLD_VTK_TMP, name) is not None


class OutDirError(ConfigError):
    """OUT cannot be used for this run (invalid input: exit 2); the message says why."""


class LockedError(OutDirError):
    """OUT is locked by another run; ``holder`` is its lock record (host, pid, started)."""

    def __init__(self, message: str, holder: dict[str, Any]):
        super().__init__(message)
        self.holder = holder


# ------------------------------------------------------------------------------------ path checks


def _first_existing(path: Path) -> Path:
    p = path
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def prepare_out_dir(out: str | Path) -> Path:
    """Create OUT (and its parents) and check that files can be created in it.

    Raises :class:`OutDirError` naming the path and the cause: OUT or one of its parents is a
    file, OUT cannot be created, OUT is not writable, or a sub-folder segmpm writes into
    (``checkpoint``, ``fields``, ``figures``) is a file."""
    out = Path(out)
    where = f"--out {str(out)!r}"
    if out.exists() and not out.is_dir():
        raise OutDirError(f"{where} exists and is not a directory (it is a file); give a "
                          "directory (new or empty) for the outputs of the run")  # fmt: skip
    if not out.exists():
        anc = _first_existing(out.parent)
        if anc.exists() and not anc.is_dir():
            raise OutDirError(f"{where} cannot be created: {str(anc)!r} is a file, not a "
                              "directory")  # fmt: skip
        try:
            out.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise OutDirError(f"{where} cannot be created: {err.strerror or err}"
                              f" ({_errno_name(err)})") from None  # fmt: skip
    for sub in SUB_FILES:
        p = out / sub
        if p.exists() and not p.is_dir():
            raise OutDirError(f"{where}: {str(p)!r} is a file, but segmpm writes its "
                              f"{sub} there (a folder); remove or rename it")  # fmt: skip
    try:  # a probe: what the run will do first (tempfile + rename), without touching anything
        fd, probe = tempfile.mkstemp(prefix=".segmpm-probe.", suffix=".tmp", dir=out)
        os.close(fd)
        os.unlink(probe)
    except OSError as err:
        raise OutDirError(f"{where}: cannot create files in this directory: "
                          f"{err.strerror or err} ({_errno_name(err)})") from None  # fmt: skip
    return out


def _errno_name(err: OSError) -> str:
    return errno.errorcode.get(err.errno, str(err.errno)) if err.errno else type(err).__name__


# ------------------------------------------------------------------------------------ own files


def own_files(out: str | Path) -> list[Path]:
    """segmpm's own files (and stray temporary files) in OUT, sorted; never the lock file."""
    out = Path(out)
    found: list[Path] = []
    if not out.is_dir():
        return found
    for p in out.iterdir():
        if p.name != LOCK_NAME and p.is_file() and _own_name("", p.name):
            found.append(p)
    for sub in SUB_FILES:
        d = out / sub
        if d.is_dir() and not d.is_symlink():
            found += [p for p in d.iterdir() if p.is_file() and _own_name(sub, p.name)]
    return sorted(found)


def foreign_files(out: str | Path) -> list[Path]:
    """Entries of OUT that are not segmpm's (a sub-folder counts only by its foreign content)."""
    out = Path(out)
    if not out.is_dir():
        return []
    own = set(own_files(out))
    found: list[Path] = []
    for p in sorted(out.iterdir()):
        if p.name == LOCK_NAME or p in own:
            continue
        if p.name in SUB_FILES and p.is_dir() and not p.is_symlink():
            found += [q for q in sorted(p.iterdir()) if q not in own]
            continue
        found.append(p)
    return found


def remove_own_files(out: str | Path) -> list[Path]:
    """Remove segmpm's own files from OUT (``--overwrite``) and the sub-folders left empty;
    every other file is kept. Returns the removed files."""
    out = Path(out)
    removed = own_files(out)
    for p in removed:
        with contextlib.suppress(FileNotFoundError):
            p.unlink()
    for sub in SUB_FILES:
        with contextlib.suppress(OSError):
            (out / sub).rmdir()  # only if empty
    return removed


def remove_stale_temporaries(out: str | Path) -> None:
    """Remove the temporary files a killed run left in OUT (call while holding the lock)."""
    for p in own_files(out):
        if p.name.startswith("."):
            with contextlib.suppress(OSError):
                p.unlink()


def read_run_info(out: str | Path) -> dict[str, Any] | None:
    """``OUT/run.json`` as a dict, or None if absent or unreadable."""
    try:
        data = json.loads((Path(out) / "run.json").read_text())
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def describe_contents(out: str | Path) -> str | None:
    """What OUT holds, in words, or None if it holds nothing (apart from a lock file)."""
    out = Path(out)
    own, foreign = own_files(out), foreign_files(out)
    if not own and not foreign:
        return None
    parts = []
    if own:
        info = read_run_info(out) or {}
        status = info.get("status")
        ckpt = (out / "checkpoint" / "state.npz").exists()
        if status == "completed":
            parts.append(f"a completed segmpm run (t = {info.get('time', float('nan')):.6g} s)")
        elif status in ("interrupted", "running", "failed"):
            state = {"running": "an unfinished (killed, or still running elsewhere)",
                     "interrupted": "an interrupted", "failed": "a failed"}[status]  # fmt: skip
            at = f"at t = {info.get('time', float('nan')):.6g} s of {info.get('time_end', '?')} s"
            parts.append(f"{state} segmpm run {at}" + (" with a checkpoint" if ckpt else ""))
        else:
            names = ", ".join(str(p.relative_to(out)) for p in own[:4])
            parts.append(f"segmpm output files ({names}{', …' if len(own) > 4 else ''})")
    if foreign:
        names = ", ".join(str(p.relative_to(out)) for p in foreign[:4])
        more = f" and {len(foreign) - 4} more" if len(foreign) > 4 else ""
        parts.append(f"files that are not segmpm's ({names}{more})")
    return " and ".join(parts)


# ------------------------------------------------------------------------------------ resume

#: configuration keys that may differ between the command line of ``--resume`` and the run in
#: OUT: they change neither the state nor the outputs (``output.dir`` is replaced by ``--out``),
#: except ``time.end``, which extends (or, before it was reached, shortens) the run
RESUME_MAY_DIFFER = ("grid.threads", "output.progress", "output.dir", "time.chunk_steps",
                     "time.end")  # fmt: skip


def _flat(data: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in data.items():
        if isinstance(v, dict):
            out.update(_flat(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def config_differences(
    old: Config, new: Config, may_differ: tuple[str, ...] = RESUME_MAY_DIFFER
) -> list[tuple[str, Any, Any]]:
    """(key, old value, new value) of every resolved key (``section.key``) that differs, except
    those in ``may_differ``."""
    a, b = _flat(old.to_dict()), _flat(new.to_dict())
    missing = object()
    return [
        (k, a.get(k, "(absent)"), b.get(k, "(absent)"))
        for k in sorted(set(a) | set(b))
        if k not in may_differ and a.get(k, missing) != b.get(k, missing)
    ]


# ------------------------------------------------------------------------------------ the lock


def _pid_alive(pid: int) -> bool:
    if pid <= 0:
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, another user's
        return True
    except OSError:
        return True
    return True


def _holder_text(holder: dict[str, Any]) -> str:
    started = holder.get("started")
    when = (
        f", started {time.strftime('%Y-%m-%d %H:%M:%S', time.localtime(started))}"
        if isinstance(started, int | float)
        else ""
    )
    return f"host {holder.get('host', '?')}, PID {holder.get('pid', '?')}{when}"


#: errno values of a filesystem without working flock (then the lock file alone is used)
NO_FLOCK = {errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL}
if hasattr(errno, "ENOTSUP"):
    NO_FLOCK.add(errno.ENOTSUP)


class OutLock:
    """An exclusive lock on an output directory, held from :meth:`acquire` to :meth:`release`
    (or as a context manager). ``mode`` is "flock" or "file" (the fallback)."""

    def __init__(self, out: str | Path):
        self.out = Path(out)
        self.path = self.out / LOCK_NAME
        self.mode: str | None = None
        self._fd: int | None = None
        self.record = {
            "host": socket.gethostname(),
            "pid": os.getpid(),
            "started": time.time(),
            "token": os.urandom(8).hex(),
        }

    def __enter__(self) -> OutLock:
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    # -- flock -------------------------------------------------------------------------
    def _read(self, fd_or_path, tries: int = 20) -> dict[str, Any]:
        for i in range(tries):  # the holder writes its record right after taking the lock
            try:
                if isinstance(fd_or_path, int):
                    raw = os.pread(fd_or_path, 4096, 0)
                else:
                    raw = Path(fd_or_path).read_bytes()
                data = json.loads(raw.decode() or "null")
                if isinstance(data, dict):
                    return data
            except (OSError, ValueError, UnicodeDecodeError):
                pass
            if i + 1 < tries:
                time.sleep(0.05)
        return {}

    def _locked(self, holder: dict[str, Any], fallback: bool) -> LockedError:
        hint = f"; if that process no longer runs, remove {str(self.path)!r}" if fallback else ""
        return LockedError(
            f"--out {str(self.out)!r} is in use by another segmpm run ({_holder_text(holder)});"
            " wait for it to end or give another --out" + hint,
            holder,
        )

    def acquire(self) -> OutLock:
        """Take the lock or raise :class:`LockedError` (OSError of the lock file: OutDirError)."""
        if self.mode is not None:
            return self
        try:
            if fcntl is not None and self._acquire_flock():
                return self
            self._acquire_file()
        except OSError as err:
            raise OutDirError(f"--out {str(self.out)!r}: cannot create the lock file "
                              f"{str(self.path)!r}: {err.strerror or err}") from None  # fmt: skip
        return self

    def _acquire_flock(self) -> bool:
        """True when held; False when the filesystem has no working flock."""
        for _ in range(50):
            created = False
            try:
                fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o666)
                created = True
            except FileExistsError:
                try:
                    fd = os.open(self.path, os.O_RDWR)
                except FileNotFoundError:  # removed by its holder meanwhile: again
                    continue
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                holder = self._read(fd)
                os.close(fd)
                raise self._locked(holder, fallback=False) from None
            except OSError as err:
                os.close(fd)
                if err.errno in NO_FLOCK:
                    if created:
                        with contextlib.suppress(OSError):
                            os.unlink(self.path)
                    return False
                raise
            # the holder before us may have removed the file after we opened it: the lock must
            # be on the file that is at the path now
            try:
                same = os.fstat(fd).st_ino == os.stat(self.path).st_ino
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
            data = json.dumps({**self.record, "mode": "flock"}).encode()
            os.ftruncate(fd, 0)
            os.pwrite(fd, data, 0)
            self._fd, self.mode = fd, "flock"
            return True
        raise OSError(errno.EAGAIN, "the lock file kept being replaced")

    # -- lock file (no flock) ----------------------------------------------------------
    def _stale(self, holder: dict[str, Any]) -> bool:
        pid = holder.get("pid")
        return (
            holder.get("host") == self.record["host"]
            and isinstance(pid, int)
            and not _pid_alive(pid)
        )

    def _acquire_file(self) -> None:
        for _ in range(10):
            try:
                fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
            except FileExistsError:
                holder = self._read(self.path)
                if holder and self._stale(holder):
                    # re-read just before removing: another process may have taken it over
                    if self._read(self.path) == holder:
                        with contextlib.suppress(FileNotFoundError):
                            os.unlink(self.path)
                    continue
                if not holder:
                    try:
                        age = time.time() - self.path.stat().st_mtime
                    except FileNotFoundError:
                        continue
                    if age > 60:  # an empty or garbled lock file nobody completed: stale
                        with contextlib.suppress(FileNotFoundError):
                            os.unlink(self.path)
                        continue
                raise self._locked(holder, fallback=True) from None
            try:
                os.write(fd, json.dumps({**self.record, "mode": "file"}).encode())
            finally:
                os.close(fd)
            self.mode = "file"
            return
        raise OSError(errno.EAGAIN, "the lock file kept being replaced")

    # -- release -----------------------------------------------------------------------
    def release(self) -> None:
        """Release the lock and remove the lock file (errors are ignored)."""
        if self.mode == "flock" and self._fd is not None:
            with contextlib.suppress(OSError):
                os.unlink(self.path)  # while still holding it (see _acquire_flock)
            with contextlib.suppress(OSError):
                os.close(self._fd)
        elif self.mode == "file":
            if self._read(self.path, tries=1).get("token") == self.record["token"]:
                with contextlib.suppress(OSError):
                    os.unlink(self.path)
        self._fd, self.mode = None, None
