"""Atomic file writes: write to a temporary sibling, fsync, then rename over the target.

An interrupted run therefore leaves either the old file or the new one, never half of one.
:func:`atomic_folder` does the same for a whole folder of outputs.
A target that cannot be written (its folder is a file, it is a folder, no permission, disk full)
raises :class:`WriteError`, a :class:`~radarslam.errors.DataError` naming the target.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import shutil
import tempfile
from collections.abc import Callable, Iterator
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


@contextlib.contextmanager
def atomic_folder(target: str | Path) -> Iterator[Path]:
    """A hidden sibling folder to write into; on clean exit it replaces ``target`` as a whole.

    A reader never sees a partial folder: an exception (Ctrl-C included) removes the sibling and
    leaves ``target`` as it was, and a re-run that writes fewer files leaves none of the previous
    run's behind. Whether ``target`` may be replaced at all is the caller's policy. Errors that
    name a file inside the sibling are re-raised naming it inside ``target``.
    """
    target = Path(target)
    _make_parent(target)
    try:
        tmp = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent))
    except OSError as exc:
        raise cannot_write(target, exc) from None
    try:
        with contextlib.suppress(OSError):
            os.chmod(tmp, folder_mode())  # mkdtemp makes 0700; outputs get the usual mode
        try:
            yield tmp
        except DataError as exc:  # name the file as the user knows it, not the temporary one
            if str(tmp) not in str(exc):
                raise
            msg = str(exc).replace(str(tmp), str(target))
            if isinstance(exc, WriteError):
                raise WriteError(msg, exc.errno) from None
            raise DataError(msg) from None
        try:
            replace_folder(tmp, target)
        except OSError as exc:
            raise cannot_write(target, exc) from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def replace_folder(new: str | Path, target: str | Path) -> None:
    """Move folder ``new`` onto ``target`` (an existing one is renamed aside, then deleted)."""
    new, target = Path(new), Path(target)
    old = None
    if target.exists():
        old = target.with_name(f".{target.name}.old-{os.getpid()}-{secrets.token_hex(4)}")
        os.rename(target, old)
    try:
        os.rename(new, target)
    except BaseException:
        if old is not None:
            os.rename(old, target)
        raise
    with contextlib.suppress(OSError):  # make the renames durable
        fd = os.open(target.parent, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


def check_output_folder(folder: str | Path, is_output: Callable[[Path], bool], what: str) -> Path:
    """Fail before any work when ``folder`` cannot be written by :func:`atomic_folder`: a file is
    in the way, its parent cannot be created or written, it is the current folder (or holds it),
    or it holds an entry that ``is_output`` does not recognise as a ``what`` (a replaced folder
    loses everything in it). Creates the parent folder; returns the folder to write (a symbolic
    link resolved, so that the link's target is what gets replaced)."""
    d = Path(folder)
    if d.is_symlink() or d.name in ("", ".", ".."):  # "." and ".." have no usable name
        d = d.resolve()
    if d.is_dir():
        try:
            cwd = Path.cwd().resolve()
        except OSError:  # the current folder was deleted
            cwd = None
        if cwd is not None and (d.resolve() == cwd or d.resolve() in cwd.parents):
            raise DataError(f"{d}: cannot replace the current folder or one holding it")
        try:
            other = sorted(e.name for e in d.iterdir() if not is_output(e))
        except OSError as exc:
            raise DataError(f"{d}: cannot read results folder ({exc.strerror})") from None
        if other:
            more = f" and {len(other) - 1} more" if len(other) > 1 else ""
            raise DataError(
                f"{d}: holds {other[0]!r}{more}, which is not a {what}; a results folder is "
                "replaced as a whole: choose a new or empty folder"
            )
    elif d.exists():
        raise DataError(f"{d}: cannot create results folder ({d} is a file, not a folder)")
    try:
        d.parent.mkdir(parents=True, exist_ok=True)
        os.rmdir(tempfile.mkdtemp(prefix=f".{d.name}.", suffix=".probe", dir=d.parent))
    except OSError as exc:
        raise DataError(f"{d}: cannot create results folder ({folder_error(d, exc)})") from None
    return d
