"""End to end: the reader on the synthetic ``tiny`` dataroot written by radarslam.sim.

Only structural invariants are checked here (the simulator's numbers belong to its own tests);
the devkit cross-check pins that the simulator's layout reads the same through both readers.
"""

from __future__ import annotations

import numpy as np
import pytest

from radarslam.nuscenes.filters import RadarPointFilter
from radarslam.nuscenes.reader import NuScenesRadar
from radarslam.nuscenes.stats import dataset_statistics
from radarslam.types import RADAR_CHANNELS


def test_tiny_dataroot_end_to_end(tiny_dataroot):
    reader = NuScenesRadar(tiny_dataroot, "v1.0-mini", use_cache=False)
    scenes = reader.scenes()
    assert scenes and reader.locations()
    assert reader.scenes_for_location(scenes[0].location)
    for info in scenes:
        for ch in RADAR_CHANNELS:
            t = [s.timestamp_us for s in reader.iter_sweeps(info, ch)]
            assert len(t) > 10 and np.all(np.diff(t) > 0)
            period_s = np.median(np.diff(t)) * 1e-6
            assert 0.06 < period_s < 0.095  # ~13 Hz
        frames = list(reader.iter_frames(info))
        used = [s.token for f in frames for s in f.sweeps.values()]
        assert len(used) == len(set(used))
        assert all(len(f.sweeps) >= 1 for f in frames)
        keys = list(reader.iter_frames(info, key_frames_only=True))
        assert len(keys) == info.nbr_samples == len(reader.samples(info))
        acc = reader.accumulate(keys[len(keys) // 2].sample_token, nsweeps=5)
        assert len(acc) == sum(acc.num_points_per_sweep.values()) > 0
        assert set(np.unique(acc.points["channel"]).tolist()) <= set(range(5))
    st = dataset_statistics(reader, max_frames_per_scene=20, progress=False)
    assert st.num_frames == 20 * len(scenes) and st.counts.num_sweeps >= st.num_frames
    assert 0.2 < st.counts.mean / st.counts.raw_mean < 0.9
    # the simulator writes exact compensated velocities: u . (v - v_comp) = -u . v_sensor holds
    # for one sensor velocity per sweep
    for k, sweep in enumerate(
        reader.iter_sweeps(scenes[0], "RADAR_FRONT", filters=RadarPointFilter.none())
    ):
        if k == 20:
            break
        u = sweep.unit_directions
        d = np.einsum("ij,ij->i", u, sweep.velocity - sweep.velocity_comp)
        v_sensor, *_ = np.linalg.lstsq(-u, d, rcond=None)
        assert np.sqrt(np.mean((d + u @ v_sensor) ** 2)) < 1e-3


def test_tiny_dataroot_matches_devkit(tiny_dataroot):
    pytest.importorskip("nuscenes")
    from nuscenes.nuscenes import NuScenes
    from nuscenes.utils.data_classes import RadarPointCloud

    reader = NuScenesRadar(tiny_dataroot, "v1.0-mini", use_cache=False)
    nusc = NuScenes("v1.0-mini", str(tiny_dataroot), verbose=False)
    sample = nusc.get("sample", reader.samples(reader.scenes()[0])[3])
    for ch in ("RADAR_FRONT", "RADAR_BACK_RIGHT"):
        pc, times = RadarPointCloud.from_file_multisweep(nusc, sample, ch, "RADAR_FRONT", nsweeps=3)
        acc = reader.accumulate(sample["token"], nsweeps=3, channels=[ch])
        assert len(acc) == pc.nbr_points()
        np.testing.assert_allclose(acc.points["x"], pc.points[0], atol=1e-6)
        np.testing.assert_allclose(acc.points["y"], pc.points[1], atol=1e-6)
        np.testing.assert_allclose(acc.points["time_lag_s"], times[0], atol=1e-6)
