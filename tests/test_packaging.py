"""A built wheel works on its own: it carries the YAML presets and the shipped weights, and once
installed outside the checkout ``radarslam simulate --preset tiny`` writes a dataroot."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
#: What the build reads; copied so that the build's own files (build/, *.egg-info) land in a
#: temporary folder rather than in the checkout, where parallel runs would share them.
BUILD_INPUTS = ("pyproject.toml", "README.md", "LICENSE", "MANIFEST.in", "setup.cfg", "setup.py")


def _run(cmd: list[str], **kwargs) -> subprocess.CompletedProcess:
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=300, **kwargs)
    assert out.returncode == 0, f"{' '.join(map(str, cmd))}\n{out.stdout}\n{out.stderr}"
    return out


@pytest.mark.slow
def test_wheel_installs_and_simulates_outside_the_checkout(tmp_path):
    assert not tmp_path.resolve().is_relative_to(REPO)
    src = tmp_path / "src"
    src.mkdir()
    for name in BUILD_INPUTS:
        if (REPO / name).is_file():
            shutil.copy2(REPO / name, src / name)
    shutil.copytree(
        REPO / "radarslam", src / "radarslam", ignore=shutil.ignore_patterns("__pycache__")
    )

    wheels = tmp_path / "wheels"
    _run(
        [sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation",
         str(src), "-w", str(wheels)]
    )  # fmt: skip
    (wheel,) = wheels.glob("radarslam-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    presets = {p.relative_to(REPO).as_posix() for p in (REPO / "radarslam/configs").rglob("*.yaml")}
    assert presets and presets <= names, sorted(presets - names)
    assert "radarslam/configs/sim/tiny.yaml" in names
    assert "radarslam/place_recognition/weights/compact.pt" in names
    assert "radarslam/place_recognition/weights/compact.json" in names
    assert not any(n.startswith("place_recognition/") for n in names)  # one top-level package

    site = tmp_path / "site"
    _run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--target", str(site),
          str(wheel)])  # fmt: skip

    # The installed copy comes first on the path; the checkout's (editable) copy must not be used.
    env = {**os.environ, "PYTHONPATH": str(site)}
    env.pop("PYTHONHOME", None)
    cwd = tmp_path / "elsewhere"
    cwd.mkdir()
    where = _run(
        [sys.executable, "-c", "import radarslam.config as c; print(c.CONFIG_DIR)"],
        env=env,
        cwd=cwd,
    )
    assert Path(where.stdout.strip()).is_relative_to(site), where.stdout

    entry = site / "bin" / "radarslam"
    command = [str(entry)] if entry.is_file() else [sys.executable, "-m", "radarslam.cli"]
    dataroot = tmp_path / "dataroot"
    _run([*command, "simulate", "--preset", "tiny", "--out", str(dataroot), "--quiet"],
         env=env, cwd=cwd)  # fmt: skip
    assert (dataroot / "v1.0-mini" / "scene.json").is_file()
    assert (dataroot / "v1.0-mini" / "sample_data.json").is_file()
    assert any((dataroot / "samples" / "RADAR_FRONT").glob("*.pcd"))
