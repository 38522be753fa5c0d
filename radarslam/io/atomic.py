"""Atomic file writes: write to a temporary sibling, fsync, then rename over the target.

An interrupted run therefore leaves either the old file or the new one, never half of one.
A target that cannot be written (its folder is a file, it is a folder, no permission, disk full)
raises :class:`WriteError`, a :class:`~radarslam.errors.DataError` naming the target.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from radarslam.errors import DataError


def _umask() -> int:
    """The process umask, read without changing it where the system tells (Linux)."""
    with contextlib.suppress(OSError, ValueError):
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def file_mode() -> int:
    """The mode a plain ``open(path, "w")`` gives a new file (0666 less the umask)."""
    return 0o666 & ~_umask()


def folder_mode() -> int:
    """The mode a plain ``mkdir`` gives a new folder (0777 less the umask)."""
    return 0o777 & ~_umask()


class WriteError(DataError, OSError):
    """A target could not be written. A :class:`DataError` (one line for the user) and still an
    ``OSError`` with the system's ``errno``, so callers that tolerate a failed write (a cache in a
    read-only folder) keep doing so."""

    def __init__(self, message: str, errno: int | None = None):
        super().__init__(message)
        self.errno = errno

    def __str__(self) -> str:
        return str(self.args[0]) if self.args else ""


def cannot_write(path: str | Path, exc: OSError, reason: str | None = None) -> WriteError:
    """``<path>: cannot write (<reason>)`` for an OSError met while writing ``path``."""
    reason = reason or exc.strerror or type(exc).__name__
    return WriteError(f"{path}: cannot write ({reason})", exc.errno)


def folder_error(folder: str | Path, exc: OSError) -> str:
    """Why ``folder`` could not be created: the file in its way, else the system's reason."""
    if isinstance(exc, (FileExistsError, NotADirectoryError)):
        folder = Path(folder)
        for p in [*reversed(folder.parents), folder]:  # from the root down
            if p.exists() and not p.is_dir():
                return f"{p} is a file, not a folder"
    return exc.strerror or type(exc).__name__


def _make_parent(path: Path) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise cannot_write(path, exc, folder_error(path.parent, exc)) from None


@contextlib.contextmanager
def atomic_open(path: str | Path, mode: str = "w", encoding: str | None = "utf-8") -> Iterator[IO]:
    """Open a temporary file next to ``path``; on clean exit it replaces ``path`` atomically."""
    path = Path(path)
    _make_parent(path)
    binary = "b" in mode
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except OSError as exc:
        raise cannot_write(path, exc) from None
    try:
        with contextlib.suppress(OSError):  # mkstemp makes 0600; outputs get the usual mode
            os.fchmod(fd, file_mode())
        with os.fdopen(fd, mode, encoding=None if binary else encoding) as fh:
            yield fh
            try:
                fh.flush()
                os.fsync(fh.fileno())
            except OSError as exc:
                raise cannot_write(path, exc) from None
        try:
            os.replace(tmp, path)
        except OSError as exc:
            raise cannot_write(path, exc) from None
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def write_text_atomic(path: str | Path, text: str) -> None:
    with atomic_open(path, "w") as fh:
        fh.write(text)


def write_bytes_atomic(path: str | Path, data: bytes) -> None:
    with atomic_open(path, "wb") as fh:
        fh.write(data)


def write_json_atomic(path: str | Path, obj: Any, indent: int | None = 2) -> None:
    with atomic_open(path, "w") as fh:
        json.dump(obj, fh, indent=indent)
        fh.write("\n")


def atomic_path(path: str | Path) -> contextlib.AbstractContextManager[Path]:
    """A temporary path to hand to a library that writes files itself (savefig, open3d, torch).

    The file is moved onto ``path`` only when the block finishes without an exception.
    """
    return _AtomicPath(Path(path))


class _AtomicPath(contextlib.AbstractContextManager):
    def __init__(self, path: Path):
        self.path = path
        self.tmp = path.with_name(f".{path.stem}.tmp{os.getpid()}{path.suffix}")

    def __enter__(self) -> Path:
        _make_parent(self.path)
        return self.tmp

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            try:
                os.replace(self.tmp, self.path)
            except OSError as err:
                with contextlib.suppress(OSError):
                    os.unlink(self.tmp)
                raise cannot_write(self.path, err) from None
        else:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.tmp)
        return False
