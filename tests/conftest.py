"""Session-wide fixtures: the synthetic ``tiny`` dataroot (generated once), config helpers and
SIGINT as Ctrl-C delivers it."""

from __future__ import annotations

import hashlib
import signal
from collections.abc import Callable
from pathlib import Path

import pytest


@pytest.fixture(scope="session", autouse=True)
def _sigint_raises_keyboard_interrupt():
    """The Ctrl-C tests need SIGINT to raise KeyboardInterrupt, here and in the processes they
    start. A test runner started in the background of a non-interactive shell inherits SIGINT
    ignored (POSIX), and Python then installs no handler; a handled signal is reset to the
    default in child processes, an ignored one stays ignored."""
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    yield


def sim_config(preset: str = "tiny", overrides: list[str] | None = None):
    """A resolved :class:`radarslam.sim.config.SimConfig` (preset plus ``key=value`` overrides)."""
    from radarslam.sim.config import load_sim_config

    return load_sim_config(preset, overrides)


@pytest.fixture(scope="session")
def tiny_dataroot(tmp_path_factory) -> Path:
    """The ``tiny`` preset (v1.0-mini: 1 log, 2 scenes of ~9 s, 5 radars), generated once."""
    from radarslam.sim import simulate

    root = tmp_path_factory.mktemp("sim_tiny")
    simulate("tiny", root, progress=False)
    return root


@pytest.fixture(scope="session")
def tiny_config():
    """The resolved tiny preset config the ``tiny_dataroot`` was generated with."""
    return sim_config("tiny")


@pytest.fixture(scope="session")
def demo_config() -> Callable:
    """``demo_config(preset="tiny", overrides=[...])`` -> SimConfig, for scenario variants."""
    return sim_config


@pytest.fixture(scope="session")
def sim_dataroot(tmp_path_factory) -> Callable[..., Path]:
    """``sim_dataroot(overrides, preset="tiny")`` -> Path: a generated variant, cached per session.

    Example: ``sim_dataroot(["schedule.scenes_per_log=1", "scenario.empty_windows=[...]"])``.
    """
    from radarslam.sim import simulate

    cache: dict[str, Path] = {}

    def make(overrides: list[str] | None = None, preset: str = "tiny") -> Path:
        key = preset + "|" + "|".join(overrides or [])
        if key not in cache:
            name = "sim_" + hashlib.md5(key.encode()).hexdigest()[:8]
            root = tmp_path_factory.mktemp(name)
            simulate(preset, root, progress=False, overrides=list(overrides or []))
            cache[key] = root
        return cache[key]

    return make


#: The real nuScenes radar split (CC BY-NC-SA: read in place, never copied into the repository).
REAL_VERSION = "v1.0-mini"


@pytest.fixture(scope="session")
def real_dataroot() -> Path:
    """``../shared/data/nuscenes-mini-radar`` beside the checkout (``RADARSLAM_REAL_DATAROOT``
    overrides it). A missing folder fails the test that needs it with this message rather than
    skipping it: the real data decides the odometry's accuracy."""
    import os

    default = Path(__file__).resolve().parents[2] / "shared" / "data" / "nuscenes-mini-radar"
    root = Path(os.environ.get("RADARSLAM_REAL_DATAROOT", default))
    if not (root / REAL_VERSION / "scene.json").is_file():
        pytest.fail(
            f"{root / REAL_VERSION}: the real nuScenes radar split is missing (expected "
            "../shared/data/nuscenes-mini-radar beside the checkout, or set "
            "RADARSLAM_REAL_DATAROOT)",
            pytrace=False,
        )
    return root


@pytest.fixture
def run_cli(capsys) -> Callable[[list[str]], tuple[object, str]]:
    """Run ``radarslam`` in this process as the console entry does (``cli.main`` with ``argv``):
    (exit code, stderr). The SIGTERM handler the CLI installs is put back afterwards."""
    import signal
    import sys

    from radarslam import cli

    def run(argv: list[str]) -> tuple[object, str]:
        old_term, old_argv = signal.getsignal(signal.SIGTERM), sys.argv
        sys.argv = ["radarslam", *argv]
        try:
            try:
                cli.main()
                code: object = 0
            except SystemExit as exc:
                code = exc.code
        finally:
            sys.argv = old_argv
            signal.signal(signal.SIGTERM, old_term)
        return code, capsys.readouterr().err

    return run
