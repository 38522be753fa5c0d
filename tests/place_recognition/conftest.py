"""Fixtures: a hand-made nuScenes-layout dataroot (the reader tests' builder) and its prepared
cache, built once per session."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from radarslam.place_recognition.config import PrepareConfig

_NUSCENES_TESTS = Path(__file__).resolve().parents[1] / "nuscenes"


def _mini_prepare_config(dataroot: Path, **kw) -> PrepareConfig:
    data = {
        "name": "mini",
        "source": {"dataroot": str(dataroot), "versions": ["v1.0-mini"],
                   "location": "boston-seaport"},
        # 3 boston scenes on 2 days: the later day is held out; short scenes -> small edges
        "split": {"time_split": "fraction", "heldout_day_fraction": 0.5, "seq_len": 2,
                  "edge_exclusion": 1, "val_fraction": 0.25},
    }  # fmt: skip
    data.update(kw)
    return PrepareConfig.model_validate(data)


@pytest.fixture(scope="session")
def mini_config():
    """``mini_config(dataroot, **section_overrides) -> PrepareConfig`` for the mini dataroot."""
    return _mini_prepare_config


@pytest.fixture(scope="session")
def mini_dataroot(tmp_path_factory) -> Path:
    sys.path.insert(0, str(_NUSCENES_TESTS))
    try:
        from mini_dataroot import build_mini_dataroot
    finally:
        sys.path.remove(str(_NUSCENES_TESTS))
    root = tmp_path_factory.mktemp("pr_mini") / "data"
    build_mini_dataroot(root)
    return root


@pytest.fixture(scope="session")
def mini_prepared(mini_dataroot, tmp_path_factory) -> Path:
    from radarslam.place_recognition.prepare import prepare

    out = tmp_path_factory.mktemp("pr_prepared")
    return prepare(_mini_prepare_config(mini_dataroot), out, progress=False)


@pytest.fixture(scope="module")
def torch_one_thread():
    """One torch thread for the whole test module, restored afterwards."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
