"""Interrupts and hard kills while outputs are put in place: an interrupt at any point leaves
the old folder (or files) or the complete new ones, and what a killed process leaves behind is
removed by the next write."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from radarslam.errors import DataError
from radarslam.io import atomic
from radarslam.io.atomic import (
    atomic_batch,
    atomic_folder,
    check_output_folder,
    interrupts_deferred,
    remove_stale_temporaries,
    write_text_atomic,
)


def _ctrl_c() -> None:
    os.kill(os.getpid(), signal.SIGINT)


def _snapshot(d):
    return {
        p.relative_to(d).as_posix(): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()
    }


def _write_folder(target, files: dict[str, str], ctrl_c_at: int | None = None):
    with atomic_folder(target) as tmp:
        for k, (name, text) in enumerate(files.items()):
            if k == ctrl_c_at:
                _ctrl_c()
            write_text_atomic(tmp / name, text)


OLD = {"run.json": "old", "a.tum": "old a", "plots/x.png": "old x"}
NEW = {"a.tum": "new a", "b.tum": "new b", "plots/x.png": "new x", "run.json": "new"}


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_interrupts_are_held_back_until_the_block_ends():
    handler = signal.getsignal(signal.SIGINT)
    reached = []
    with pytest.raises(KeyboardInterrupt):
        with interrupts_deferred():
            _ctrl_c()
            _ctrl_c()
            reached.append("end of block")
    assert reached == ["end of block"]
    assert signal.getsignal(signal.SIGINT) is handler


@pytest.mark.parametrize("at", range(len(NEW)))
def test_ctrl_c_while_a_folder_is_written_leaves_the_old_one(tmp_path, at):
    out = tmp_path / "res"
    _write_folder(out, OLD)
    before = _snapshot(out)
    with pytest.raises(KeyboardInterrupt):
        _write_folder(out, NEW, ctrl_c_at=at)
    assert _snapshot(out) == before
    assert [p.name for p in tmp_path.iterdir()] == ["res"]


@pytest.mark.parametrize("exchange", [True, False], ids=["exchange", "two-renames"])
def test_ctrl_c_during_the_swap_completes_it_first(tmp_path, monkeypatch, exchange):
    out = tmp_path / "res"
    _write_folder(out, OLD)
    real_rename, real_exchange = os.rename, atomic._exchange
    if exchange:
        if not real_exchange(tmp_path, tmp_path):  # a no-op swap: does this system have it?
            pytest.skip("no renameat2(RENAME_EXCHANGE) here")

        def interrupted_exchange(a, b):
            _ctrl_c()
            return real_exchange(a, b)

        monkeypatch.setattr(atomic, "_exchange", interrupted_exchange)
    else:
        monkeypatch.setattr(atomic, "_exchange", lambda a, b: False)

        def interrupted_rename(a, b):  # between the old folder moved aside and the new one in
            real_rename(a, b)
            _ctrl_c()

        monkeypatch.setattr(atomic.os, "rename", interrupted_rename)
    with pytest.raises(KeyboardInterrupt):
        _write_folder(out, NEW)
    monkeypatch.undo()
    assert _snapshot(out) == {k: v.encode() for k, v in NEW.items()}
    assert [p.name for p in tmp_path.iterdir()] == ["res"]


def test_a_kill_between_the_two_renames_is_repaired_by_the_next_write(tmp_path):
    # what the fallback swap leaves when killed between its renames: the old folder aside,
    # the new one beside it, no folder at the target
    dead = _dead_pid()
    out = tmp_path / "res"
    _write_folder(out, OLD)
    os.rename(out, tmp_path / f".res.{dead}-1a2b3c4d.old")
    _write_folder(tmp_path / f".res.{dead}-abcdefgh.tmp", NEW)
    check_output_folder(out, lambda p: True, "result file")
    assert _snapshot(out) == {k: v.encode() for k, v in OLD.items()}  # the last complete folder
    assert [p.name for p in tmp_path.iterdir()] == ["res"]


def test_what_a_killed_run_left_is_removed_and_a_running_ones_kept(tmp_path):
    dead = _dead_pid()
    out = tmp_path / "res"
    _write_folder(out, OLD)
    (tmp_path / f".res.{dead}-abcdefgh.tmp" / "plots").mkdir(parents=True)  # kill -9 mid-run
    (tmp_path / f".res.{dead}-12345678.old").mkdir()  # kill -9 before the old one was deleted
    (tmp_path / f".res.{os.getpid()}-running.tmp").mkdir()  # a run in progress
    (tmp_path / f".other.{dead}-abcdefgh.tmp").mkdir()  # another output's
    (tmp_path / ".res.abcdefgh.tmp").mkdir()  # no process id: nothing says it is stale
    _write_folder(out, NEW)
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        [f".other.{dead}-abcdefgh.tmp", f".res.{os.getpid()}-running.tmp",
         ".res.abcdefgh.tmp", "res"]
    )  # fmt: skip
    assert _snapshot(out) == {k: v.encode() for k, v in NEW.items()}


def test_a_killed_process_leaves_temporaries_named_after_it(tmp_path):
    # a real kill -9 in the middle of writing a folder: its temporary folder carries its id
    out = tmp_path / "res"
    code = (
        "import os, signal, sys\n"
        "from radarslam.io.atomic import atomic_folder, write_text_atomic\n"
        "with atomic_folder(sys.argv[1]) as tmp:\n"
        "    write_text_atomic(tmp / 'a.tum', 'half')\n"
        "    os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    proc = subprocess.Popen([sys.executable, "-c", code, str(out)])
    assert proc.wait() == -signal.SIGKILL
    left = [p.name for p in tmp_path.iterdir()]
    assert left == [f".res.{proc.pid}-{left[0].split('-', 1)[1]}"] and left[0].endswith(".tmp")
    assert remove_stale_temporaries(tmp_path) == [tmp_path / left[0]]
    assert list(tmp_path.iterdir()) == []


# --- files that belong together ------------------------------------------------------------------


def _write_files(d, files, ctrl_c_at=None, fail_at=None):
    with atomic_batch():
        for k, (name, text) in enumerate(files.items()):
            if k == ctrl_c_at:
                _ctrl_c()
            if k == fail_at:
                raise RuntimeError("disk on fire")
            write_text_atomic(d / name, text)


@pytest.mark.parametrize("at", range(len(NEW)))
def test_a_batch_interrupted_or_failing_leaves_every_old_file(tmp_path, at):
    _write_files(tmp_path, OLD)
    before = _snapshot(tmp_path)
    with pytest.raises(KeyboardInterrupt):
        _write_files(tmp_path, NEW, ctrl_c_at=at)
    assert _snapshot(tmp_path) == before
    with pytest.raises(RuntimeError):
        _write_files(tmp_path, NEW, fail_at=at)
    assert _snapshot(tmp_path) == before


def test_ctrl_c_while_a_batch_is_put_in_place_completes_it(tmp_path, monkeypatch):
    _write_files(tmp_path, OLD)
    real_replace = os.replace
    calls = []

    def interrupted_replace(a, b):
        calls.append(b)
        if len(calls) == 1:
            _ctrl_c()
        real_replace(a, b)

    monkeypatch.setattr(atomic.os, "replace", interrupted_replace)
    with pytest.raises(KeyboardInterrupt):
        _write_files(tmp_path, NEW)
    monkeypatch.undo()
    assert len(calls) == len(NEW)
    assert _snapshot(tmp_path) == {k: v.encode() for k, v in (OLD | NEW).items()}


def test_a_batch_removes_stale_temporaries_of_its_files(tmp_path):
    dead = _dead_pid()
    (tmp_path / f".metrics.json.{dead}-abcdefgh.tmp").write_text("half")
    (tmp_path / f".x.png.{dead}-0a1b2c3d.tmp.png").write_text("half")  # from atomic_path
    (tmp_path / f".notes.txt.{dead}-abcdefgh.tmp").write_text("not written here")
    _write_files(tmp_path, {"metrics.json": "{}", "x.png": "png"})
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        f".notes.txt.{dead}-abcdefgh.tmp",
        "metrics.json",
        "x.png",
    ]


# --- folders that cannot be replaced fail before any work ----------------------------------------


def test_a_mount_point_is_refused_before_any_work(tmp_path, monkeypatch):
    out = tmp_path / "res"
    out.mkdir()
    monkeypatch.setattr(atomic.os.path, "ismount", lambda p: str(p) == str(out))
    with pytest.raises(
        DataError, match=r"res: cannot replace results folder \(it is a mount point"
    ):
        check_output_folder(out, lambda p: True, "result file")


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes anywhere")
def test_an_unwritable_folder_is_refused_before_any_work(tmp_path):
    out = tmp_path / "res"
    out.mkdir()
    out.chmod(0o555)
    try:
        with pytest.raises(DataError, match=r"res: cannot replace results folder \(not writable"):
            check_output_folder(out, lambda p: True, "result file")
    finally:
        out.chmod(0o755)


@pytest.mark.parametrize("maker", ["mkdtemp", "mkstemp"])
def test_ctrl_c_as_a_temporary_is_created_leaves_nothing(tmp_path, monkeypatch, maker):
    real = getattr(atomic.tempfile, maker)

    def interrupted(*args, **kwargs):
        made = real(*args, **kwargs)
        _ctrl_c()  # held back until the name is known
        return made

    monkeypatch.setattr(atomic.tempfile, maker, interrupted)
    with pytest.raises(KeyboardInterrupt):
        if maker == "mkdtemp":
            _write_folder(tmp_path / "res", NEW)
        else:
            write_text_atomic(tmp_path / "metrics.json", "{}")
    assert list(tmp_path.iterdir()) == []
