"""Writer -> reader round trip: the project's reader sees exactly what the generator wrote."""

from __future__ import annotations

import json

import numpy as np
import pytest

from radarslam.geometry import make_transform
from radarslam.nuscenes.pcd import read_pcd
from radarslam.sim.generate import CHANNELS

reader_mod = pytest.importorskip("radarslam.nuscenes.reader")
filters_mod = pytest.importorskip("radarslam.nuscenes.filters")

VERSION = "v1.0-mini"


def test_reader_round_trip(tiny_dataroot):
    root = tiny_dataroot
    reader = reader_mod.NuScenesRadar(
        root, VERSION, filters=filters_mod.RadarPointFilter.none(), use_cache=False
    )
    scenes = reader.scenes()
    tables = {
        n: json.loads((root / VERSION / f"{n}.json").read_text())
        for n in ("scene", "sample_data", "ego_pose", "calibrated_sensor", "log")
    }
    assert [s.name for s in scenes] == [s["name"] for s in tables["scene"]]
    assert scenes[0].location == "synth-seaport"
    assert scenes[0].date_captured == tables["log"][0]["date_captured"]
    sd = {r["token"]: r for r in tables["sample_data"]}
    poses = {r["token"]: r for r in tables["ego_pose"]}
    cal = {r["token"]: r for r in tables["calibrated_sensor"]}
    n_checked = 0
    for scene in scenes:
        for ch in CHANNELS:
            sweeps = list(reader.iter_sweeps(scene, ch))
            assert len(sweeps) > 50
            ts = [s.timestamp_us for s in sweeps]
            assert ts == sorted(ts)
            for sw in sweeps[::7]:
                rec = sd[sw.token]
                assert sw.timestamp_us == rec["timestamp"]
                assert sw.is_key_frame == rec["is_key_frame"]
                want = read_pcd(root / rec["filename"])
                assert np.array_equal(sw.points, want)
                p = poses[rec["ego_pose_token"]]
                np.testing.assert_allclose(
                    sw.world_from_ego, make_transform(p["translation"], p["rotation"]), atol=1e-12
                )
                c = cal[rec["calibrated_sensor_token"]]
                np.testing.assert_allclose(
                    sw.ego_from_sensor, make_transform(c["translation"], c["rotation"]), atol=1e-12
                )
                n_checked += 1
    assert n_checked > 100
    # With the reader's default (devkit) filters roughly half of the points remain.
    default = reader_mod.NuScenesRadar(root, VERSION, use_cache=False)
    sw_all = list(reader.iter_sweeps(scenes[0], "RADAR_FRONT"))
    sw_def = list(default.iter_sweeps(scenes[0], "RADAR_FRONT"))
    frac = sum(len(s) for s in sw_def) / sum(len(s) for s in sw_all)
    assert 0.35 < frac < 0.7
