"""Atomic file writes: write to a temporary sibling, fsync, then rename over the target.

An interrupted run therefore leaves either the old file or the new one, never half of one.
:func:`atomic_folder` does the same for a whole folder of outputs, and :func:`atomic_batch` for
several files that belong together. The final renames run with Ctrl-C and SIGTERM held back
(:func:`interrupts_deferred`): an interrupt there takes effect once they are done.
A target that cannot be written (its folder is a file, it is a folder, no permission, disk full)
raises :class:`WriteError`, a :class:`~radarslam.errors.DataError` naming the target; so do a
block device and a socket. A FIFO or character device (``--json /dev/stdout``, a pipe) is
written in place, as a stream: a rename would put a plain file where it is. A symbolic link is
written through: the file it points to is replaced, the link stays.

Temporary names carry the writing process's id, ``.<target name>.<pid>-<random>.tmp`` (a
folder moved aside: ``....old``): what a process killed hard (``kill -9``) leaves behind is
recognised as stale once that process is gone, and removed by the next write of the same folder
(:func:`remove_stale_temporaries`).
"""

from __future__ import annotations

import contextlib
import contextvars
import json
import os
import re
import secrets
import shutil
import stat
import sys
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


def _temp_prefix(name: str) -> str:
    """Prefix of a temporary sibling of ``name`` written by this process."""
    return f".{name}.{os.getpid()}-"


#: ``.<name>.<pid>-<random>.tmp`` (optionally followed by the target's suffix, for libraries
#: that choose a format by it) or ``.<name>.<pid>-<random>.old``.
_TEMP_NAME = re.compile(
    r"^\.(?P<name>.+)\.(?P<pid>\d+)-[A-Za-z0-9_]+\.(?P<kind>tmp|old)(?:\.[^.]+)?$"
)


def _process_exists(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:  # another user's (no permission to signal it): it runs
        return True
    return True


def remove_stale_temporaries(folder: str | Path, names: set[str] | None = None) -> list[Path]:
    """Remove the temporary files and folders in ``folder`` that a process no longer running
    left behind (killed before it could clean up), for the targets ``names`` (None: all).

    A previous results folder moved aside (``.<name>.<pid>-*.old``) while its target ``<name>``
    is missing is what a kill between the two renames of a swap leaves: it is moved back, the
    last complete folder. Returns what was removed or restored. Best effort: what cannot be
    removed stays."""
    folder = Path(folder)
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return []
    stale = []
    for e in entries:
        m = _TEMP_NAME.match(e.name)
        if m is None or (names is not None and m["name"] not in names):
            continue
        if not _process_exists(int(m["pid"])):
            stale.append((e, m))
    done = []
    for e, m in sorted(stale, key=lambda em: _mtime(em[0]), reverse=True):  # newest first
        target = folder / m["name"]
        if m["kind"] == "old" and not os.path.lexists(target):
            with contextlib.suppress(OSError):
                os.rename(e.path, target)
                done.append(target)
                continue
        if e.is_dir(follow_symlinks=False):
            shutil.rmtree(e.path, ignore_errors=True)
        else:
            with contextlib.suppress(OSError):
                os.unlink(e.path)
        done.append(Path(e.path))
    return done


def _mtime(entry: os.DirEntry) -> float:
    try:
        return entry.stat(follow_symlinks=False).st_mtime
    except OSError:
        return 0.0


@contextlib.contextmanager
def interrupts_deferred() -> Iterator[None]:
    """Hold back Ctrl-C and SIGTERM for the block: one that arrives meanwhile is delivered
    once it ends (a KeyboardInterrupt then, after the work). For the few renames that put
    finished outputs in place, which must not stop half-way. Python handles signals in the main
    thread only, so elsewhere this does nothing; a handler not set from Python is left alone."""
    import signal
    import threading

    if threading.current_thread() is not threading.main_thread():
        yield
        return
    held: list[int] = []

    def hold(signum, frame) -> None:
        held.append(signum)

    previous: dict[int, Any] = {}
    try:
        for sig in (signal.SIGINT, signal.SIGTERM):
            if signal.getsignal(sig) is not None:
                previous[sig] = signal.signal(sig, hold)
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        for signum in dict.fromkeys(held):
            signal.raise_signal(signum)


#: Renames (temporary file, target) waiting for the end of the innermost :func:`atomic_batch`.
_BATCH: contextvars.ContextVar[list[tuple[Path, Path]] | None] = contextvars.ContextVar(
    "atomic_batch", default=None
)


def _put_in_place(tmp: Path | str, path: Path) -> None:
    """Rename a finished temporary file onto its target, now or at the end of the batch."""
    pending = _BATCH.get()
    if pending is not None:
        pending.append((Path(tmp), path))
        return
    os.replace(tmp, path)


@contextlib.contextmanager
def atomic_batch() -> Iterator[None]:
    """Files written atomically in the block (:func:`atomic_open`, the ``write_*_atomic``
    functions, :func:`atomic_path`) replace their targets together when it ends, with
    interrupts held back: an interrupt at any point, or an error in the block, leaves all the
    old files or all the new ones (``radarslam eval``'s metrics and plots; only a rename that
    fails while they are put in place, which a folder swap would avoid, can leave some of each).
    Inside the block a target still reads as the old file. Stale temporary files of the same
    targets are removed at the end. A batch inside a batch is part of the outer one."""
    if _BATCH.get() is not None:
        yield
        return
    pending: list[tuple[Path, Path]] = []
    token = _BATCH.set(pending)
    try:
        yield
    except BaseException:
        _BATCH.reset(token)
        _unlink_all(tmp for tmp, _ in pending)
        raise
    _BATCH.reset(token)
    done = 0
    try:
        with interrupts_deferred():
            for tmp, path in pending:
                try:
                    os.replace(tmp, path)
                except OSError as exc:
                    raise cannot_write(path, exc) from None
                done += 1
            for parent in dict.fromkeys(path.parent for _, path in pending):
                _fsync_folder(parent)
    finally:
        _unlink_all(tmp for tmp, _ in pending[done:])
    by_folder: dict[Path, set[str]] = {}
    for _, path in pending:
        by_folder.setdefault(path.parent, set()).add(path.name)
    for parent, names in by_folder.items():
        remove_stale_temporaries(parent, names)


def _unlink_all(paths) -> None:
    for tmp in paths:
        with contextlib.suppress(OSError):
            os.unlink(tmp)


def _fsync_folder(folder: Path) -> None:
    """Make the renames in ``folder`` durable (best effort)."""
    with contextlib.suppress(OSError):
        fd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)


def _target(path: Path) -> tuple[Path, bool]:
    """(the file an atomic write replaces, whether it is a stream). A symbolic link is written
    through (the link stays a link). A FIFO or character device (``/dev/stdout``, a pipe) is a
    stream: written in place, since a rename would put a plain file where it is. A block device
    or socket is refused."""
    try:
        st = os.stat(path)  # follows links
    except FileNotFoundError:
        # a dangling link: where it points
        return (Path(os.path.realpath(path)) if path.is_symlink() else path), False
    except OSError:
        return path, False  # the write itself reports why (no permission, a file in the way)
    if stat.S_ISFIFO(st.st_mode) or stat.S_ISCHR(st.st_mode):
        return path, True
    if stat.S_ISBLK(st.st_mode) or stat.S_ISSOCK(st.st_mode):
        kind = "a block device" if stat.S_ISBLK(st.st_mode) else "a socket"
        raise WriteError(f"{path}: cannot write (it is {kind}, not a file)")
    return (Path(os.path.realpath(path)) if path.is_symlink() else path), False


def _open_stream(path: Path, mode: str, encoding: str | None) -> IO:
    try:
        return open(path, mode, encoding=None if "b" in mode else encoding)
    except OSError as exc:
        raise cannot_write(path, exc) from None


def _make_parent(path: Path) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise cannot_write(path, exc, folder_error(path.parent, exc)) from None


@contextlib.contextmanager
def atomic_open(path: str | Path, mode: str = "w", encoding: str | None = "utf-8") -> Iterator[IO]:
    """Open a temporary file next to ``path``; on clean exit it replaces ``path`` atomically.
    A FIFO or character device is written in place (a stream has no old content to keep)."""
    path, stream = _target(Path(path))
    if stream:
        with _open_stream(path, mode, encoding) as fh:
            yield fh
        return
    _make_parent(path)
    binary = "b" in mode
    fd = tmp = None
    try:
        with interrupts_deferred():  # the file and its name, which the cleanup needs, together
            fd, tmp = tempfile.mkstemp(
                prefix=_temp_prefix(path.name), suffix=".tmp", dir=path.parent
            )
    except BaseException as exc:
        if fd is not None and tmp is not None:
            os.close(fd)
            os.unlink(tmp)
        if isinstance(exc, OSError):
            raise cannot_write(path, exc) from None
        raise
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
            _put_in_place(tmp, path)
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
        self.path, self.stream = _target(path)
        path = self.path
        # the target's suffix last: savefig and open3d choose the format by it
        name = f"{_temp_prefix(path.name)}{secrets.token_hex(4)}.tmp{path.suffix}"
        # a stream's folder (/dev) is no place for a file: the system's temporary folder is
        self.tmp = Path(tempfile.gettempdir(), name) if self.stream else path.with_name(name)

    def __enter__(self) -> Path:
        if not self.stream:
            _make_parent(self.path)
        return self.tmp

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None and self.stream:  # what the library wrote, copied into the stream
            try:
                with open(self.tmp, "rb") as src, _open_stream(self.path, "wb", None) as dst:
                    shutil.copyfileobj(src, dst)
            except OSError as err:
                raise cannot_write(self.path, err) from None
            finally:
                with contextlib.suppress(OSError):
                    os.unlink(self.tmp)
        elif exc_type is None:
            try:
                _put_in_place(self.tmp, self.path)
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
    remove_stale_temporaries(target.parent, {target.name})
    tmp = None
    try:
        with interrupts_deferred():  # the folder and its name, which the cleanup needs, together
            tmp = Path(
                tempfile.mkdtemp(prefix=_temp_prefix(target.name), suffix=".tmp", dir=target.parent)
            )
    except BaseException as exc:
        if tmp is not None:
            os.rmdir(tmp)
        if isinstance(exc, OSError):
            raise cannot_write(target, exc) from None
        raise
    try:
        with contextlib.suppress(OSError):
            os.chmod(tmp, folder_mode())  # mkdtemp makes 0700; outputs get the usual mode
        # files inside go in place at once: the folder as a whole is the atomic step
        outer_batch = _BATCH.set(None)
        try:
            yield tmp
        except DataError as exc:  # name the file as the user knows it, not the temporary one
            if str(tmp) not in str(exc):
                raise
            msg = str(exc).replace(str(tmp), str(target))
            if isinstance(exc, WriteError):
                raise WriteError(msg, exc.errno) from None
            raise DataError(msg) from None
        finally:
            _BATCH.reset(outer_batch)
        try:
            replace_folder(tmp, target)
        except OSError as exc:
            raise cannot_write(target, exc) from None
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def replace_folder(new: str | Path, target: str | Path) -> None:
    """Move folder ``new`` onto ``target``, interrupts held back (:func:`interrupts_deferred`).

    Where the system can (Linux, most local file systems), the two folders are exchanged in one
    step, so that even ``kill -9`` leaves the old folder or the new one; elsewhere the old one is
    renamed aside first (a kill between the two renames leaves it aside, and the next write
    moves it back: :func:`remove_stale_temporaries`). The old folder is deleted afterwards."""
    new, target = Path(new), Path(target)
    aside = None  # the previous folder, once out of the way
    try:
        with interrupts_deferred():
            if os.path.lexists(target):
                if _exchange(new, target):
                    aside = new
                else:
                    moved = target.with_name(
                        f"{_temp_prefix(target.name)}{secrets.token_hex(4)}.old"
                    )
                    os.rename(target, moved)
                    try:
                        os.rename(new, target)
                    except BaseException:
                        os.rename(moved, target)
                        raise
                    aside = moved
            else:
                os.rename(new, target)
            _fsync_folder(target.parent)
    finally:
        if aside is not None:
            shutil.rmtree(aside, ignore_errors=True)


_RENAME_EXCHANGE = 2  # renameat2(2) flag
_AT_FDCWD = -100
_renameat2: Any = None


def _exchange(a: Path, b: Path) -> bool:
    """Swap paths ``a`` and ``b`` atomically (Linux renameat2 with RENAME_EXCHANGE). False
    where it cannot be done (another system, an old C library or kernel, a file system without
    it, or any other failure, which the plain renames then report)."""
    global _renameat2
    if not sys.platform.startswith("linux"):
        return False
    if _renameat2 is None:
        import ctypes

        try:
            _renameat2 = ctypes.CDLL(None, use_errno=True).renameat2
        except (OSError, AttributeError):
            _renameat2 = False
    if _renameat2 is False:
        return False
    return _renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0


def check_output_folder(folder: str | Path, is_output: Callable[[Path], bool], what: str) -> Path:
    """Fail before any work when ``folder`` cannot be written by :func:`atomic_folder`: a file is
    in the way, its parent cannot be created or written, it is the current folder (or holds it),
    it cannot be replaced (a mount point, or not writable), or it holds an entry that
    ``is_output`` does not recognise as a ``what`` (a replaced folder loses everything in it).
    Creates the parent folder and removes what killed earlier runs left beside the folder
    (:func:`remove_stale_temporaries`); returns the folder to write (a symbolic link resolved,
    so that the link's target is what gets replaced)."""
    d = Path(folder)
    if d.is_symlink() or d.name in ("", ".", ".."):  # "." and ".." have no usable name
        d = d.resolve()
    remove_stale_temporaries(d.parent, {d.name})
    if d.is_dir():
        try:
            cwd = Path.cwd().resolve()
        except OSError:  # the current folder was deleted
            cwd = None
        if cwd is not None and (d.resolve() == cwd or d.resolve() in cwd.parents):
            raise DataError(f"{d}: cannot replace the current folder or one holding it")
        if os.path.ismount(d):
            raise DataError(
                f"{d}: cannot replace results folder (it is a mount point, which cannot be "
                "renamed; a results folder is replaced as a whole): choose a folder inside it"
            )
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
        if not os.access(d, os.W_OK | os.X_OK):  # its files could not be deleted once replaced
            raise DataError(f"{d}: cannot replace results folder (not writable)")
    elif d.exists():
        raise DataError(f"{d}: cannot create results folder ({d} is a file, not a folder)")
    try:
        d.parent.mkdir(parents=True, exist_ok=True)
        with interrupts_deferred():  # never leave the probe behind
            os.rmdir(tempfile.mkdtemp(prefix=_temp_prefix(d.name), suffix=".tmp", dir=d.parent))
    except OSError as exc:
        raise DataError(f"{d}: cannot create results folder ({folder_error(d, exc)})") from None
    return d
