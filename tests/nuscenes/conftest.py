"""Fixtures of the nuScenes reader tests: one hand-made dataroot per session, clones to damage."""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent))

from mini_dataroot import VERSION, MiniTruth, build_mini_dataroot

from radarslam.nuscenes.reader import NuScenesRadar


@pytest.fixture(scope="session")
def mini(tmp_path_factory) -> MiniTruth:
    return build_mini_dataroot(tmp_path_factory.mktemp("mini_nuscenes"))


@pytest.fixture()
def reader(mini) -> NuScenesRadar:
    return NuScenesRadar(mini.dataroot, VERSION, use_cache=False)


@pytest.fixture()
def clone(mini, tmp_path):
    """A copy of the mini dataroot whose tables (and, on request, .pcd files) can be damaged."""

    def make(copy_files: bool = False) -> Path:
        root = tmp_path / "clone"
        shutil.copytree(mini.dataroot / VERSION, root / VERSION)
        for sub in ("samples", "sweeps", "maps"):
            if copy_files:
                shutil.copytree(mini.dataroot / sub, root / sub)
            else:
                os.symlink(mini.dataroot / sub, root / sub)
        return root

    return make
