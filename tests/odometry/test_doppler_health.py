"""``run_odometry`` says, once per scene, when the Doppler fits are implausible."""

from __future__ import annotations

import logging
import re
import shutil

import numpy as np

from radarslam.nuscenes.pcd import pcd_bytes, read_pcd
from radarslam.nuscenes.reader import NuScenesRadar
from radarslam.odometry.run import DopplerHealth, run_odometry


def _garbage_doppler(src, dst):
    shutil.copytree(src, dst)
    rng = np.random.default_rng(0)
    for path in sorted(dst.glob("s*/RADAR_*/*.pcd")):
        pts = read_pcd(path)
        for key in ("vx", "vy", "vx_comp", "vy_comp"):
            pts[key] = rng.uniform(-20.0, 20.0, len(pts))
        path.write_bytes(pcd_bytes(pts))
    return dst


def test_garbage_doppler_is_said_once_per_scene(tiny_dataroot, tmp_path, caplog):
    reader = NuScenesRadar(tiny_dataroot, "v1.0-mini", use_cache=False)
    names = [s.name for s in reader.scenes()]

    def said():
        return [r.getMessage() for r in caplog.records if r.name == "radarslam.odometry"]

    with caplog.at_level(logging.WARNING, logger="radarslam.odometry"):
        run_odometry(reader, names, progress=False)
    assert not said()  # the clean drives: no word

    bad = NuScenesRadar(_garbage_doppler(tiny_dataroot, tmp_path / "garbage"), "v1.0-mini")
    with caplog.at_level(logging.WARNING, logger="radarslam.odometry"):
        run_odometry(bad, names, progress=False)
    messages = said()
    assert len(messages) == len(names), messages
    for name, msg in zip(names, messages, strict=True):
        # (a scene may also have too few valid fits: both reasons are then given)
        assert msg.startswith(f"scene {name}: ") and msg.endswith("its odometry is unreliable")
        assert re.search(r"the Doppler fits keep only [0-9]% of their points as static-world", msg)


def test_a_radar_without_any_sweep_is_named(tiny_dataroot, tmp_path, caplog):
    import json

    root = tmp_path / "renamed"
    shutil.copytree(tiny_dataroot, root)
    table = root / "v1.0-mini" / "sensor.json"
    sensors = json.loads(table.read_text())
    for s in sensors:
        if s["channel"] == "RADAR_FRONT":
            s["channel"] = "RADAR_TOP"  # not a radar channel this reader knows
    table.write_text(json.dumps(sensors))
    reader = NuScenesRadar(root, "v1.0-mini", use_cache=False)
    name = reader.scenes()[0].name
    with caplog.at_level(logging.WARNING, logger="radarslam.odometry"):
        run_odometry(reader, [name], progress=False, max_frames_per_scene=20)
    said = [r.getMessage() for r in caplog.records if r.name == "radarslam.odometry"]
    assert said == [
        f"scene {name}: no sweep from RADAR_FRONT: the odometry runs on the other radars"
    ]


class _Fit:
    def __init__(self, valid, inliers, points):
        self.valid, self.num_inliers, self.num_points = valid, inliers, points


def test_doppler_health_thresholds():
    h = DopplerHealth(min_points=3)
    for _ in range(10):
        h.add(_Fit(True, 80, 100))
    h.add(_Fit(False, 0, 2))  # too few points for a fit: not counted
    assert h.problem() is None
    for _ in range(11):
        h.add(_Fit(False, 0, 50))
    assert h.problem().startswith("only 10 of 21 frames have a valid Doppler fit")
    assert "inliers" not in h.problem()
    for _ in range(5):
        h.add(_Fit(True, 1, 1000))
        h.add(_Fit(False, 0, 50))
        h.add(_Fit(False, 0, 50))
    both = h.problem()
    assert both.startswith("only 15 of 36 frames") and "; the Doppler fits keep only 13% " in both
    none_valid = DopplerHealth()
    none_valid.add(_Fit(False, 0, 50))
    assert none_valid.problem() == (
        "only 0 of 1 frames have a valid Doppler fit (0%; expected at least 50%)"
    )
    assert DopplerHealth().problem() is None  # no frame with points: nothing to say


def test_slam_run_says_it_too(tiny_dataroot, tmp_path):
    """``radarslam run`` (its odometry runs in a forked process) warns the same way."""
    import subprocess
    import sys

    bad = _garbage_doppler(tiny_dataroot, tmp_path / "garbage")
    proc = subprocess.run(
        [sys.executable, "-m", "radarslam.cli", "run", "--dataroot", str(bad), "--version",
         "v1.0-mini", "--out", str(tmp_path / "res"), "--no-loops", "--no-progress",
         "--no-evaluate"],
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if "static-world inliers" in ln]
    assert len(lines) == 2 and all("unreliable" in ln for ln in lines), proc.stderr
