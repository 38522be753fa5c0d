"""bench/degraded.py: the knocked-out-of-line condition turns one radar's written extrinsic."""

import importlib.util
import json
import sys
from pathlib import Path

import numpy as np
import pytest

from radarslam.geometry import quat_to_rotation

BENCH = Path(__file__).resolve().parents[1] / "bench"


@pytest.fixture
def degraded(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))  # its sibling helpers (_cli, odometry)
    spec = importlib.util.spec_from_file_location("bench_degraded", BENCH / "degraded.py")
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "bench_degraded", module)  # its dataclasses look it up
    spec.loader.exec_module(module)
    return module


def _yaw_deg(rotation) -> float:
    r = quat_to_rotation(np.asarray(rotation, dtype=np.float64))
    return float(np.degrees(np.arctan2(r[1, 0], r[0, 0])))


def test_one_channels_extrinsics_turn_about_the_vertical_and_no_other_file_changes(
    degraded, tmp_path
):
    src = tmp_path / "src"
    tables = src / "v1.0-mini"
    tables.mkdir(parents=True)
    sensors = [
        {"token": "s-front", "channel": "RADAR_FRONT", "modality": "radar"},
        {"token": "s-left", "channel": "RADAR_FRONT_LEFT", "modality": "radar"},
    ]
    half = np.deg2rad(88.0) / 2  # the front-left unit looks 88 deg to the left
    calib = [
        {"token": "c1", "sensor_token": "s-front", "translation": [3.4, 0, 0.5],
         "rotation": [1.0, 0.0, 0.0, 0.0], "camera_intrinsic": []},
        {"token": "c2", "sensor_token": "s-left", "translation": [2.4, 0.8, 0.5],
         "rotation": [np.cos(half), 0.0, 0.0, np.sin(half)], "camera_intrinsic": []},
    ]  # fmt: skip
    (tables / "sensor.json").write_text(json.dumps(sensors))
    (tables / "calibrated_sensor.json").write_text(json.dumps(calib))
    (src / "sweeps").mkdir()
    (src / "sweeps" / "a.pcd").write_bytes(b"points")

    dst = tmp_path / "dst"
    degraded.degraded_root(src, dst, set(), "RADAR_FRONT_LEFT", "v1.0-mini")
    out = json.loads((dst / "v1.0-mini" / "calibrated_sensor.json").read_text())
    assert out[0] == calib[0]
    assert _yaw_deg(out[1]["rotation"]) == pytest.approx(88.0 + degraded.TURN_DEG, abs=1e-9)
    assert np.linalg.norm(out[1]["rotation"]) == pytest.approx(1.0, abs=1e-12)
    assert out[1]["translation"] == calib[1]["translation"]
    # the source is untouched; every other file is a link to it
    assert json.loads((tables / "calibrated_sensor.json").read_text()) == calib
    assert (dst / "sweeps" / "a.pcd").is_symlink()
    assert (dst / "v1.0-mini" / "sensor.json").is_symlink()
    assert not (dst / "v1.0-mini" / "calibrated_sensor.json").is_symlink()


def test_every_radar_gets_a_turned_condition(degraded):
    names = [name for name, spec in degraded.conditions(["RADAR_FRONT", "RADAR_BACK_LEFT"])
             if "turned" in spec]  # fmt: skip
    assert names == ["RADAR_FRONT off 3 deg", "RADAR_BACK_LEFT off 3 deg"]
