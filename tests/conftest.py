"""Session-wide fixtures: the synthetic ``tiny`` dataroot (generated once) and config helpers."""

from __future__ import annotations

import hashlib
from collections.abc import Callable
from pathlib import Path

import pytest


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
