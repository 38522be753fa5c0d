"""``radarslam.cli.main``: one-line errors, Ctrl-C and SIGTERM."""

from __future__ import annotations

import os
import signal
import sys

import pytest
import typer

from radarslam import cli
from radarslam.io.atomic import atomic_open


@pytest.fixture
def run_main(monkeypatch):
    """``run_main(fn)`` -> (exit code, stderr): ``cli.main`` with ``fn`` as the only command."""
    old_term = signal.getsignal(signal.SIGTERM)

    def not_installed(signum, frame):  # fails the test instead of killing pytest
        raise RuntimeError("cli.main did not install its SIGTERM handler")

    def run(fn, capsys):
        signal.signal(signal.SIGTERM, not_installed)
        app = typer.Typer(add_completion=False, pretty_exceptions_enable=False)
        app.command("go")(fn)
        app.command("other")(lambda: None)  # two commands: "go" is a sub-command
        monkeypatch.setattr(cli, "app", app)
        monkeypatch.setattr(sys, "argv", ["radarslam", "go"])
        try:
            with pytest.raises(SystemExit) as exc:
                cli.main()
        finally:
            signal.signal(signal.SIGTERM, old_term)
        return exc.value.code, capsys.readouterr().err

    return run


def test_uncaught_oserror_is_one_line(run_main, capsys, tmp_path):
    def go():
        open(tmp_path / "missing" / "x.txt", "w")

    code, err = run_main(go, capsys)
    assert code == 2
    assert err == f"error: {tmp_path / 'missing' / 'x.txt'}: No such file or directory\n"


def test_ctrl_c_prints_interrupted(run_main, capsys):
    def go():
        raise KeyboardInterrupt

    code, err = run_main(go, capsys)
    assert code == 130 and err.strip() == "interrupted"


def test_sigterm_acts_like_ctrl_c_and_cleans_up_temporary_files(run_main, capsys, tmp_path):
    target = tmp_path / "out.json"

    def go():
        with atomic_open(target) as fh:
            fh.write("half")
            os.kill(os.getpid(), signal.SIGTERM)
            fh.write("never")

    code, err = run_main(go, capsys)
    assert code == 130 and err.strip() == "interrupted"
    assert list(tmp_path.iterdir()) == []  # neither the target nor a temporary file


@pytest.mark.parametrize(
    ("argv", "expected"),
    [
        (
            ["run", "--out", "x", "--dataset", "foo"],
            "error: Invalid value for '--dataset': 'foo' is not one of 'nuscenes', 'synthetic'",
        ),
        (
            ["run", "--out", "x", "--max-scenes", "0"],
            "error: Invalid value for '--max-scenes': Input should be greater than or equal to 1",
        ),
        (["bogus"], "error: No such command 'bogus'"),
        (["run"], "error: Missing option '--out'"),
        (["run", "--out"], "error: Option '--out' requires an argument"),
    ],
)
def test_usage_errors_are_one_line(monkeypatch, capsys, tmp_path, argv, expected):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "argv", ["radarslam", *argv])
    old_term = signal.getsignal(signal.SIGTERM)
    try:
        with pytest.raises(SystemExit) as exc:
            cli.main()
    finally:
        signal.signal(signal.SIGTERM, old_term)
    err = capsys.readouterr().err
    assert exc.value.code == 2
    assert err.startswith(expected) and err.count("\n") == 1, err
    assert list(tmp_path.iterdir()) == []


def test_help_still_exits_zero(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["radarslam", "run", "--help"])
    old_term = signal.getsignal(signal.SIGTERM)
    try:
        cli.main()
    except SystemExit as exc:
        assert exc.code in (0, None)
    finally:
        signal.signal(signal.SIGTERM, old_term)
    assert "--dataroot" in capsys.readouterr().out
