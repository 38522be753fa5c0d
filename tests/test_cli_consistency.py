"""Every command of the ``radarslam`` app selects data the same way and fails the same way.

Walks the typer app, so a new command is checked without being listed here: ``--version`` has one
default, ``--scenes`` one form (a comma-separated string, one help text), there is no singular
``--scene``, and bad input ends as one ``error:`` line on stderr with exit status 2.
"""

from __future__ import annotations

import re
import signal
import sys
from pathlib import Path

import pytest
from typer.main import get_command

from radarslam import cli
from radarslam.nuscenes.commands import SCENES_HELP, VERSION_DEFAULT

ROOT = Path(__file__).resolve().parents[1]


def _leaf_commands():
    """(command path, click command) of every command that runs something."""
    out = []

    def walk(cmd, path):
        subs = getattr(cmd, "commands", None)
        if subs:
            for name, sub in subs.items():
                walk(sub, [*path, name])
        else:
            out.append((" ".join(path), cmd))

    walk(get_command(cli.app), [])
    return out


def _option(cmd, flag: str):
    return next((p for p in cmd.params if flag in getattr(p, "opts", ())), None)


COMMANDS = _leaf_commands()
WITH_SCENES = [(name, cmd) for name, cmd in COMMANDS if _option(cmd, "--scenes") is not None]


def test_the_walk_finds_the_commands():
    names = [name for name, _ in COMMANDS]
    for expected in ("run", "odometry", "stats", "pr build-db", "pr query"):
        assert expected in names
    assert {name for name, _ in WITH_SCENES} >= {"run", "odometry", "stats", "pr build-db"}


@pytest.mark.parametrize("name,cmd", COMMANDS, ids=[n for n, _ in COMMANDS])
def test_version_and_scenes_options_are_the_same_everywhere(name, cmd):
    version = _option(cmd, "--version")
    if version is not None:
        assert version.default == VERSION_DEFAULT, f"{name} --version"
    scenes = _option(cmd, "--scenes")
    if scenes is not None:
        assert scenes.help == SCENES_HELP, f"{name} --scenes"
        assert not scenes.multiple and scenes.default is None, f"{name} --scenes"
    assert _option(cmd, "--scene") is None, f"{name}: --scene; use --scenes a,b"


def _main(argv: list[str], capsys) -> tuple[int, str]:
    old_term = signal.getsignal(signal.SIGTERM)
    old_argv = sys.argv
    sys.argv = ["radarslam", *argv]
    try:
        with pytest.raises(SystemExit) as exc:
            cli.main()
    finally:
        sys.argv = old_argv
        signal.signal(signal.SIGTERM, old_term)
    return exc.value.code, capsys.readouterr().err


def _required_args(cmd, tmp_path: Path) -> list[str]:
    """Stand-ins for the required parameters: paths that do not exist."""
    args: list[str] = []
    for p in cmd.params:
        if p.required:
            value = str(tmp_path / f"no_{p.name}")
            flag = next((o for o in p.opts if o.startswith("-")), None)
            args += [flag, value] if flag else [value]
    return args


@pytest.mark.parametrize("name,cmd", WITH_SCENES, ids=[n for n, _ in WITH_SCENES])
def test_bad_input_is_one_error_line(name, cmd, tmp_path, capsys):
    code, err = _main([*name.split(), *_required_args(cmd, tmp_path), "--scenes", "a,,b"], capsys)
    assert code == 2, err
    assert re.fullmatch(r"error: [^\n]+\n", err), err


def test_only_the_cli_ends_the_process_or_prints_errors():
    """Commands raise RadarSlamError; radarslam/cli.py alone turns it into ``error:`` and an
    exit status."""
    pattern = re.compile(r"sys\.exit\(|typer\.Exit\(|raise SystemExit|[\"']error: ")
    offenders = [
        f"{path.relative_to(ROOT)}:{i}"
        for path in sorted((ROOT / "radarslam").rglob("*.py"))
        if path.name != "cli.py" or path.parent.name != "radarslam"
        for i, line in enumerate(path.read_text().splitlines(), 1)
        if pattern.search(line)
    ]
    assert not offenders, offenders


def test_run_synthetic_takes_the_presets_version_unless_one_is_given(tmp_path, monkeypatch):
    from typer.testing import CliRunner

    from radarslam.slam import commands

    generated, runs = [], []
    monkeypatch.setattr(
        commands, "ensure_synthetic", lambda preset, root, progress: generated.append(preset) or "v"
    )
    monkeypatch.setattr(commands, "run_slam", lambda root, version, *a, **k: runs.append(version))
    base = ["run", "--dataset", "synthetic", "--dataroot", str(tmp_path / "d"), "--no-progress"]
    for extra in ([], ["--version", VERSION_DEFAULT]):
        out = ["--out", str(tmp_path / f"r{len(runs)}")]
        result = CliRunner().invoke(cli.app, [*base, *out, *extra], catch_exceptions=False)
        assert result.exit_code == 0, result.output
    # the default: the preset's tables, generated; a version given: a copy made earlier
    assert generated == ["demo"] and runs == ["v", VERSION_DEFAULT]
