"""``radarslam.cli.main``: an interrupt that surfaces as another exception is still an
interruption (one ``interrupted`` line, exit status 130, no traceback)."""

from __future__ import annotations

import sys

import pytest
import typer

from radarslam import cli


def _main_with(fn, monkeypatch, capsys) -> tuple[int, str]:
    app = typer.Typer(add_completion=False, pretty_exceptions_enable=False)
    app.command("go")(fn)
    app.command("other")(lambda: None)  # two commands: "go" is a sub-command
    monkeypatch.setattr(cli, "app", app)
    monkeypatch.setattr(sys, "argv", ["radarslam", "go"])
    monkeypatch.setattr(cli, "_install_sigterm_handler", lambda: None)
    with pytest.raises(SystemExit) as exc:
        cli.main()
    return exc.value.code, capsys.readouterr().err


def test_an_import_cut_short_by_ctrl_c_is_an_interruption(monkeypatch, capsys):
    def go():  # what a compiled module's initialisation does when Ctrl-C arrives in it
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as exc:
            raise ImportError("initialization failed") from exc

    code, err = _main_with(go, monkeypatch, capsys)
    assert (code, err) == (130, "interrupted\n")


def test_an_error_raised_while_handling_ctrl_c_is_an_interruption(monkeypatch, capsys):
    def go():
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise OSError(5, "Input/output error") from None

    code, err = _main_with(go, monkeypatch, capsys)
    assert (code, err) == (130, "interrupted\n")


def test_other_errors_are_not_interruptions(monkeypatch, capsys):
    def go():
        raise ImportError("no module named nothing")

    with pytest.raises(ImportError):
        _main_with(go, monkeypatch, capsys)
