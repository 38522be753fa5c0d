"""The SLAM run's helper processes: the radar reading and the odometry of a pipelined run
(:mod:`radarslam.slam.feed`) and the calibration pass (:mod:`radarslam.slam.calibration_pass`).

They are forked, so nothing they are given is pickled. Each starts with
:func:`helper_process_setup` (Ctrl-C left to the parent, SIGTERM ends it at once, it dies with its
parent, lower priority), hands an error to its parent as a :class:`Failed` message
(:func:`put_error`), and is stopped and collected by :func:`end_helper`.
"""

from __future__ import annotations

import os
import sys
import time
from contextlib import contextmanager
from dataclasses import dataclass

from radarslam.errors import DataError


@dataclass(frozen=True)
class Failed:
    """A helper process's error, raised again by the process that receives it."""

    error: BaseException


def end_helper(proc, stop_now: bool) -> None:
    """Wait for a helper process to end; with ``stop_now`` SIGTERM it first (which ends it at
    once, :func:`helper_process_setup`); one still alive after 5 s is killed."""
    if stop_now and proc.is_alive():
        proc.terminate()
    proc.join(timeout=5.0)
    if proc.is_alive():
        proc.kill()
        proc.join()


@contextmanager
def one_torch_thread():
    """torch's intra-op pool down to one thread while the odometry process has the other core:
    two threads then only contend (12-scene city run: 31 s with one, 38 s with two). Yields a
    function that gives the pool its threads back, for when the odometry process is done."""
    torch = sys.modules.get("torch")  # never imported just for this
    if torch is None:
        yield lambda: None
        return
    previous = torch.get_num_threads()
    torch.set_num_threads(1)

    def restore() -> None:
        if torch.get_num_threads() != previous:
            torch.set_num_threads(previous)

    try:
        yield restore
    finally:
        restore()


def can_fork() -> bool:
    import multiprocessing as mp

    return "fork" in mp.get_all_start_methods()


#: Niceness added to the reading and odometry processes. On two cores the three processes share
#: the cores, and the key-frame side (recognition, verification, iSAM2), the longest serial chain,
#: fell behind while the other two ran, then caught up alone with one core idle for ~10 s at the
#: end. Lower priority for the other two lets it keep up: the benchmark's run went from 14.4-14.8x
#: to 15.1-15.8x real time in interleaved runs, identical results. With more cores than busy
#: processes it changes nothing.
HELPER_NICENESS = 5


def _lower_priority() -> None:
    try:
        os.nice(HELPER_NICENESS)
    except (AttributeError, OSError):  # no nice() here: the run is only slower
        pass


#: prctl(2) option: the signal a process receives when its parent dies (Linux).
_PR_SET_PDEATHSIG = 1

#: Seconds between two checks of the parent where prctl is not available.
PARENT_CHECK_S = 0.5


def die_with_parent(parent: int, pdeathsig: bool = True) -> None:
    """End this forked process when ``parent`` dies, whatever it is doing then.

    A parent killed hard (``kill -9``, the OOM killer) runs no cleanup: a helper blocked on a
    full queue or in its queue's feeder would wait forever, reparented to init. Linux kills it
    with SIGKILL (nothing of a helper's needs cleaning up: its queues die with the run);
    elsewhere a thread notices the new parent id within :data:`PARENT_CHECK_S`. The parent may
    have died before this runs, hence the check after prctl."""
    armed = False
    if pdeathsig and sys.platform.startswith("linux"):
        import ctypes
        import signal

        try:
            libc = ctypes.CDLL(None, use_errno=True)
            armed = libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0) == 0
        except (OSError, AttributeError):  # no prctl in this libc: the thread below
            armed = False
    if os.getppid() != parent:
        os._exit(1)
    if armed:
        return
    import threading

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(PARENT_CHECK_S)
        os._exit(1)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def helper_process_setup(parent: int) -> None:
    """First thing the reading and odometry processes do. Ctrl-C reaches every process of the
    terminal's process group: the helpers ignore it (a second one would otherwise print their
    tracebacks) and the parent, which gets the KeyboardInterrupt, stops them. SIGTERM
    (``Process.terminate``) ends them at once, even inside compiled code, instead of going
    through a Python handler inherited from the command line."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    die_with_parent(parent)
    _lower_priority()


#: Seconds between two collections of ended helper processes by the parent.
REAP_EVERY_S = 0.5


def put_error(queue, exc: BaseException, what: str) -> None:
    try:
        queue.put(Failed(exc))
    except Exception:  # an unpicklable error: say what it was
        queue.put(Failed(DataError(f"{what}: {type(exc).__name__}: {exc}")))
