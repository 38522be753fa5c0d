"""Ctrl-C during ``radarslam run``, as a terminal sends it (to the whole process group): one
``interrupted`` line, exit status 130, and the results folder is the previous one or the
complete new one, whenever the interrupt comes."""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="needs /proc")

RADARSLAM = str(Path(sys.executable).with_name("radarslam"))


def _run(dataroot, out, *extra) -> list[str]:
    return [RADARSLAM, "run", "--dataroot", str(dataroot), "--version", "v1.0-mini",
            "--out", str(out), "--max-scenes", "1", "--no-loops", "--no-progress",
            *extra]  # fmt: skip


def _snapshot(d: Path) -> dict[str, bytes]:
    return {
        p.relative_to(d).as_posix(): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()
    }


@pytest.fixture(scope="module")
def previous_results(tiny_dataroot, tmp_path_factory) -> Path:
    """A results folder without evaluation: a complete new one has metrics.json."""
    out = tmp_path_factory.mktemp("previous") / "res"
    subprocess.run(_run(tiny_dataroot, out, "--no-evaluate"), check=True, capture_output=True)
    assert not (out / "metrics.json").exists()
    return out


def _children(pid: int) -> list[int]:
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            with contextlib.suppress(OSError):
                text = Path(f"/proc/{entry}/stat").read_text()
                if int(text.rsplit(")", 1)[1].split()[1]) == pid:
                    found.append(int(entry))
    return found


def _new_run_json(proc, out: Path, old_inode: int) -> bool:
    """A new run.json exists: in the folder being written, or already swapped in."""
    if any(out.parent.glob(f".{out.name}.*.tmp/run.json")):
        return True
    with contextlib.suppress(OSError):
        return (out / "run.json").stat().st_ino != old_inode
    return False


MOMENTS = {
    # the calibration pass (the preset's), the first helper process and the only one then
    "calibration": lambda proc, out, inode: len(_children(proc.pid)) == 1,
    # the odometry and reading processes running; Ctrl-C pressed twice
    "slam": lambda proc, out, inode: len(_children(proc.pid)) == 2,
    # the results being written (their hidden folder exists)
    "writing": lambda proc, out, inode: any(out.parent.glob(f".{out.name}.*.tmp")),
    # everything but the evaluation written
    "evaluation": _new_run_json,
}


@pytest.mark.parametrize("moment", list(MOMENTS))
def test_ctrl_c_leaves_the_previous_folder_or_the_complete_new_one(
    tiny_dataroot, previous_results, tmp_path, moment
):
    out = tmp_path / "res"
    shutil.copytree(previous_results, out)
    before = _snapshot(out)
    inode = (out / "run.json").stat().st_ino
    proc = subprocess.Popen(
        _run(tiny_dataroot, out),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        start_new_session=True,  # its own process group, like a terminal's foreground job
    )
    try:
        deadline = time.monotonic() + 60
        while not MOMENTS[moment](proc, out, inode):
            assert proc.poll() is None, f"the run ended before the {moment} step was seen"
            assert time.monotonic() < deadline
            time.sleep(0.002)
        os.killpg(proc.pid, signal.SIGINT)
        pressed = time.monotonic()
        if moment == "slam":
            time.sleep(0.1)
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGINT)
        _, err = proc.communicate(timeout=60)
        if moment == "calibration":  # the helper is stopped at once, not waited for
            assert time.monotonic() - pressed < 4.0
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    err = err.decode()
    assert proc.returncode == 130, err
    assert err.splitlines()[-1] == "interrupted", err
    assert "Traceback" not in err and "Exception" not in err and "Error" not in err, err
    after = _snapshot(out)
    if after != before:  # then the complete new folder
        assert {"run.json", "metrics.json", "map.ply", "plots/trajectories.png"} <= set(after)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]  # nothing hidden left


def _mount_read_only_tmpfs(where: Path) -> bool:
    if os.geteuid() != 0 or shutil.which("mount") is None:
        return False
    where.mkdir()
    done = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "ro,size=1m", "tmpfs", str(where)], capture_output=True
    )
    return done.returncode == 0


def test_a_read_only_mount_point_as_out_fails_before_the_run(tiny_dataroot, tmp_path):
    out = tmp_path / "mnt"
    if not _mount_read_only_tmpfs(out):
        pytest.skip("cannot mount a file system here")
    try:
        t0 = time.monotonic()
        done = subprocess.run(_run(tiny_dataroot, out), capture_output=True, text=True)
        took = time.monotonic() - t0
    finally:
        subprocess.run(["umount", str(out)], check=True)
    assert done.returncode == 2, done.stderr
    assert done.stderr.splitlines() == [
        f"error: {out}: cannot replace results folder (it is a mount point, which cannot be "
        "renamed; a results folder is replaced as a whole): choose a folder inside it"
    ]
    assert took < 5.0  # no SLAM run first


def test_what_a_run_killed_hard_leaves_a_rerun_removes(tiny_dataroot, previous_results, tmp_path):
    out = tmp_path / "res"
    shutil.copytree(previous_results, out)
    before = _snapshot(out)
    proc = subprocess.Popen(
        _run(tiny_dataroot, out), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
    )
    try:
        deadline = time.monotonic() + 60
        while not any(tmp_path.glob(".res.*.tmp/run.json")):  # the new folder, before the swap
            assert proc.poll() is None and time.monotonic() < deadline
            time.sleep(0.002)
        proc.kill()
    finally:
        proc.kill()
        proc.wait()
    left = sorted(p.name for p in tmp_path.iterdir())
    assert left[-1] == "res" and len(left) == 2 and left[0].startswith(f".res.{proc.pid}-")
    assert _snapshot(out) == before
    subprocess.run(_run(tiny_dataroot, out, "--no-evaluate"), check=True, capture_output=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]
