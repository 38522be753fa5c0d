"""The SLAM pipeline's helper processes end with their parent, however it ends.

The checks run with this test process as the *child subreaper* (Linux): a helper whose parent
dies is then reparented here rather than to init, so the test can see it and collect it
(an init that does not reap, as in some containers, would otherwise keep it as a zombie).
"""

from __future__ import annotations

import contextlib
import ctypes
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="needs /proc, prctl")

_PR_SET_CHILD_SUBREAPER = 36
RADARSLAM = str(Path(sys.executable).with_name("radarslam"))


@contextlib.contextmanager
def subreaper():
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(_PR_SET_CHILD_SUBREAPER, 1, 0, 0, 0) != 0:
        pytest.skip("prctl(PR_SET_CHILD_SUBREAPER) not permitted")
    try:
        yield
    finally:
        libc.prctl(_PR_SET_CHILD_SUBREAPER, 0, 0, 0, 0)


def _stat(pid: int) -> tuple[str, int] | None:
    """(state, parent pid) from /proc, None once the process is gone."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = text.rsplit(")", 1)[1].split()
    return fields[0], int(fields[1])


def _children(pid: int) -> list[int]:
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            st = _stat(int(entry))
            if st is not None and st[1] == pid:
                found.append(int(entry))
    return sorted(found)


def _collect(pids, timeout_s: float) -> set[int]:
    """Wait for ``pids`` (our children now) to end; those still running after ``timeout_s``."""
    left = set(pids)
    deadline = time.monotonic() + timeout_s
    while left and time.monotonic() < deadline:
        for pid in list(left):
            try:
                done, _ = os.waitpid(pid, os.WNOHANG)
            except ChildProcessError:  # not ours: gone, or collected elsewhere
                done = pid
            if done:
                left.discard(pid)
        time.sleep(0.01)
    return left


def _kill_and_collect(pids) -> None:
    for pid in pids:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)
    _collect(pids, 5.0)


def test_helpers_die_with_a_run_killed_hard(tiny_dataroot, tmp_path):
    # With loop closure on, the key-frame side lags: the reader blocks on its full queue and the
    # odometry fills its own. A helper blocked like that when its parent is killed waits for
    # ever unless something ends it.
    cmd = [RADARSLAM, "run", "--dataroot", str(tiny_dataroot), "--version", "v1.0-mini",
           "--out", str(tmp_path / "res"), "--max-scenes", "1", "--no-evaluate",
           "--no-progress"]  # fmt: skip
    with subreaper():
        main = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        helpers: list[int] = []
        try:
            deadline = time.monotonic() + 60
            while len(helpers) < 2 and time.monotonic() < deadline:
                helpers = _children(main.pid)
                time.sleep(0.01)
            assert len(helpers) == 2, "the run never started its reading and odometry processes"
            time.sleep(1.0)  # mid-run: queues filling
            assert all(_stat(pid) is not None for pid in helpers), "helpers ended before the kill"
            main.kill()
            main.wait()
            left = _collect(helpers, 3.0)
        finally:
            if main.poll() is None:
                main.kill()
                main.wait()
            _kill_and_collect(helpers)
    assert not left, f"helper process(es) {sorted(left)} outlived the killed run"


def test_without_prctl_a_helper_notices_its_parent_is_gone():
    from radarslam.slam import processes

    with subreaper():
        r, w = os.pipe()
        child = os.fork()
        if child == 0:  # the parent-to-be-killed: starts a helper, then dies
            try:
                parent = os.getpid()  # not the helper's getppid(): the parent may be gone by then
                helper = os.fork()
                if helper == 0:
                    processes.die_with_parent(parent, pdeathsig=False)
                    time.sleep(30)
                    os._exit(0)
                os.write(w, str(helper).encode())
            finally:
                os._exit(0)
        os.close(w)
        helper = int(os.read(r, 32))
        os.close(r)
        os.waitpid(child, 0)
        t0 = time.monotonic()
        left = _collect([helper], 3.0)
        took = time.monotonic() - t0
        _kill_and_collect(left)
    assert not left, "the helper kept running after its parent died"
    assert took < 2 * processes.PARENT_CHECK_S + 0.5
