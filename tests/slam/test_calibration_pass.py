"""The SLAM calibration pass: when it stops, what it reports, which frames it drives."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

import radarslam.odometry.pipeline as odometry_pipeline
from radarslam.nuscenes.reader import NuScenesRadar
from radarslam.odometry.config import OdometryConfig
from radarslam.slam.calibration_pass import (
    PASS_PROJECTION_SLACK,
    CalibrationPassResult,
    count_rigs,
    estimate_calibration,
)
from radarslam.types import SceneInfo


class _Calibration:
    def __init__(self, sigma: float):
        self.sigma = sigma

    def as_dict(self) -> dict:
        return {"mounting_yaw_sigma_deg": {"RADAR_FRONT": self.sigma, "RADAR_BACK_LEFT": 0.01}}


def _fake_odometry(sigmas: list[float]):
    """An odometry whose sigma after scene k is ``sigmas[k]`` (one frame per scene)."""

    class FakeOdometry:
        def __init__(self, config):
            self.scene = -1
            self.calibration = _Calibration(np.nan)

        def reset(self) -> None:
            self.scene += 1

        def fold_calibration(self) -> None:
            self.scene += 1

        def process(self, frame) -> None:
            self.calibration = _Calibration(sigmas[self.scene])

    return FakeOdometry


class _Reader:
    """One frame per scene; scenes ``gap_s`` apart (end of one to the start of the next)."""

    def __init__(self, gap_s: float = 100.0):
        self.gap_s = gap_s

    def iter_frames(self, info, filters=None):
        k = int(info.name.split("-")[1])
        yield SimpleNamespace(name=info.name, timestamp_us=round(k * self.gap_s * 1e6))

    def scene_extrinsics(self, info):
        return {}  # no rig: one car assumed


def _scenes(n: int, samples: int = 40) -> list[SceneInfo]:
    return [
        SceneInfo(f"scene-{i:04d}", f"t{i}", "log", "city", "2026-01-01", "car", samples, "a", "b")
        for i in range(n)
    ]


def _run(monkeypatch, sigmas, max_sigma_deg, n=None):
    monkeypatch.setattr(odometry_pipeline, "RadarOdometry", _fake_odometry(sigmas))
    scenes = _scenes(n or len(sigmas))
    return estimate_calibration(_Reader(), scenes, OdometryConfig(), None, max_sigma_deg)


def test_the_pass_stops_once_below_the_limit(monkeypatch):
    # 1/sqrt(drive time): 0.3 after one scene of nine reaches 0.1 after the ninth
    sigmas = [0.3 / np.sqrt(k) for k in range(1, 10)]
    found = _run(monkeypatch, [*sigmas[:-1], 0.0999], 0.1)
    assert found.converged and found.scenes_used == found.scenes_total == 9
    assert found.max_sigma_deg == pytest.approx(0.0999)
    found = _run(monkeypatch, [0.5, 0.05, 0.04], 0.1)
    assert found.converged and found.scenes_used == 2


def test_the_pass_stops_when_the_scenes_left_cannot_get_there(monkeypatch):
    # after 2 of 6 equal scenes, 0.4 projects to 0.4 * sqrt(2/6) = 0.23 > 2 x 0.1
    found = _run(monkeypatch, [1.0, 0.4, 0.3, 0.3, 0.3, 0.3], 0.1)
    assert not found.converged and (found.scenes_used, found.scenes_total) == (2, 6)
    assert found.max_sigma_deg == pytest.approx(0.4)
    # within the slack it goes on: 0.3 * sqrt(2/6) = 0.17 < 0.2
    found = _run(monkeypatch, [1.0, 0.3, 0.25, 0.2, 0.15, 0.12], 0.1)
    assert not found.converged and found.scenes_used == 6
    # the first scene alone never stops it (the filter may not have left its prior yet)
    found = _run(monkeypatch, [1.0, 0.09], 0.1)
    assert found.converged and found.scenes_used == 2
    assert PASS_PROJECTION_SLACK == 2.0


def test_without_a_limit_the_pass_runs_every_scene(monkeypatch):
    found = _run(monkeypatch, [1.0, 0.9, 0.8, 0.7], None)
    assert found.converged and found.scenes_used == 4
    assert found.max_sigma_deg == pytest.approx(0.7)


def test_the_pass_drives_on_through_a_log_cut_into_contiguous_scenes(monkeypatch):
    """Scenes of one log that follow within the odometry's gap limit are one drive for the pass,
    as for the run (``continue_log_scenes``): the odometry is reset once, not per scene."""
    resets = []

    class Counting(_fake_odometry([1.0] * 4)):  # type: ignore[misc]
        def reset(self) -> None:
            resets.append(1)
            super().reset()

        def process(self, frame) -> None:
            self.calibration = _Calibration(1.0)

    monkeypatch.setattr(odometry_pipeline, "RadarOdometry", Counting)
    gap_s = 0.5 * OdometryConfig().fusion.max_gap_s
    estimate_calibration(_Reader(gap_s), _scenes(4), OdometryConfig(), None, None)
    assert len(resets) == 1
    resets.clear()
    estimate_calibration(
        _Reader(gap_s), _scenes(4), OdometryConfig(), None, None, continue_log_scenes=False
    )
    assert len(resets) == 4
    resets.clear()  # farther apart than the gap limit: each scene its own drive
    estimate_calibration(_Reader(10.0), _scenes(4), OdometryConfig(), None, None)
    assert len(resets) == 4


def test_no_pass_over_scenes_of_several_cars(real_dataroot):
    """One set of mounting yaws cannot serve two cars: over a Boston and a Singapore scene the
    pass does not run and says why (``rigs``)."""
    reader = NuScenesRadar(real_dataroot, "v1.0-mini")
    infos = [reader.scene(name) for name in ("scene-0103", "scene-0061")]
    assert count_rigs(reader, infos[:1]) == 1
    assert count_rigs(reader, [infos[0], reader.scene("scene-0655")]) == 1
    found = estimate_calibration(reader, infos, OdometryConfig(), None, 0.1)
    assert found.rigs == 2 and found.scenes_used == 0 and not found.converged


def test_a_continued_scene_skips_the_frames_already_driven(monkeypatch):
    """Scenes that share their boundary frame: the pass drives each frame once, in time order."""
    from radarslam.slam.feed import after

    frames = [SimpleNamespace(timestamp_us=t) for t in (10, 20, 30)]
    assert [f.timestamp_us for f in after(frames, 20)] == [30]
    assert [f.timestamp_us for f in after(frames, None)] == [10, 20, 30]
    assert list(after(frames, 30)) == []

    class Overlapping(_Reader):  # scene k: frames at k and k + 1 s, the next starts on k + 1 s
        def iter_frames(self, info, filters=None):
            k = int(info.name.split("-")[1])
            for t in (k, k + 1):
                yield SimpleNamespace(name=info.name, timestamp_us=t * 1_000_000)

    driven: list[int] = []

    class Recording(_fake_odometry([1.0] * 4)):  # type: ignore[misc]
        def process(self, frame) -> None:
            driven.append(frame.timestamp_us)
            self.calibration = _Calibration(1.0)

    monkeypatch.setattr(odometry_pipeline, "RadarOdometry", Recording)
    every = OdometryConfig.model_validate({"fusion": {"calibration": {"pass_frame_stride": 1}}})
    estimate_calibration(Overlapping(), _scenes(3), every, None, None)
    assert driven == [0, 1_000_000, 2_000_000, 3_000_000]
    # pass_frame_stride: every k-th frame of a drive, counted on through the scenes it continues
    driven.clear()
    estimate_calibration(Overlapping(), _scenes(3), OdometryConfig(), None, None)
    assert OdometryConfig().fusion.calibration.pass_frame_stride == 3
    assert driven == [0, 3_000_000]
    second = OdometryConfig.model_validate({"fusion": {"calibration": {"pass_frame_stride": 2}}})
    driven.clear()
    estimate_calibration(Overlapping(), _scenes(3), second, None, None)
    assert driven == [0, 2_000_000]


def test_the_forked_pass_leaves_the_readers_notes_to_the_run(monkeypatch, capfd):
    import logging
    import sys

    from radarslam.slam import calibration_pass as cp

    def estimate(*args, **kwargs):
        logging.getLogger("radarslam.nuscenes").warning("scene-0000: 1 empty sweep(s) yielded")
        logging.getLogger("radarslam.slam").warning("a note of the pass itself")
        return CalibrationPassResult({}, True, 1, 1)

    monkeypatch.setattr(cp, "estimate_calibration", estimate)
    handler = logging.StreamHandler(sys.stderr)  # as the CLI's: the forked pass inherits it
    root = logging.getLogger()
    root.addHandler(handler)
    try:
        result = cp.calibration_pass(None, _scenes(1), None, None, 0.1, forked=True)
    finally:
        root.removeHandler(handler)
    err = capfd.readouterr().err
    assert result == CalibrationPassResult({}, True, 1, 1)
    assert "a note of the pass itself" in err
    assert "empty sweep" not in err
    assert logging.getLogger("radarslam.nuscenes").getEffectiveLevel() <= logging.WARNING
