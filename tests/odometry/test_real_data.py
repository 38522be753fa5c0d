"""The odometry on real nuScenes radar (two scenes of ../shared/data): error bounds pinned on the
numbers bench/odometry.py reports, and ours against the kiss-icp peer on the same frames."""

from __future__ import annotations

import numpy as np
import pytest

from radarslam.eval import metrics as m
from radarslam.nuscenes.reader import NuScenesRadar
from radarslam.odometry.config import OdometryConfig
from radarslam.odometry.run import run_odometry, write_outputs


@pytest.fixture(scope="module")
def reader(real_dataroot) -> NuScenesRadar:
    return NuScenesRadar(real_dataroot, "v1.0-mini")


def _errors(traj) -> tuple[float, float]:
    ate = m.ate(traj.poses, traj.ground_truth, align="se2").rmse_m
    rpe10 = m.rpe(traj.poses, traj.ground_truth, None, 10.0, "m").trans_rmse_m
    return ate, rpe10


@pytest.mark.parametrize(
    ("scene", "max_ate_m", "max_rpe10_m"),
    # Measured 0.076 / 0.095 m and 0.095 / 0.092 m (ATE / RPE per 10 m).
    [("scene-0061", 0.10, 0.125), ("scene-0103", 0.125, 0.12)],
)
def test_ours_on_real_scene(reader, scene, max_ate_m, max_rpe10_m):
    ours = run_odometry(reader, [scene], progress=False)
    peer = run_odometry(reader, [scene], method="kiss-icp", progress=False)
    ate, rpe10 = _errors(ours)
    peer_ate, peer_rpe10 = _errors(peer)
    assert len(ours) > 250
    assert ate < max_ate_m, f"{scene}: ATE {ate:.3f} m"
    assert rpe10 < max_rpe10_m, f"{scene}: RPE 10 m {rpe10:.3f} m"
    # On these two scenes ours beats the peer on both (0.076 vs 0.123 m, 0.095 vs 0.142 m ATE).
    assert ate < peer_ate and rpe10 < peer_rpe10


def test_doppler_heading_on_real_boston_scene(reader):
    """The Doppler fit's integrated heading over scene-0103 (19 s) stays within 0.3 deg/s of the
    ground truth (measured -0.2 deg)."""
    traj = run_odometry(reader, ["scene-0103"], method="doppler", progress=False)
    yaw = np.unwrap(np.arctan2(traj.poses[:, 1, 0], traj.poses[:, 0, 0]))
    yaw_gt = np.unwrap(np.arctan2(traj.ground_truth[:, 1, 0], traj.ground_truth[:, 0, 0]))
    err_deg = np.degrees((yaw[-1] - yaw[0]) - (yaw_gt[-1] - yaw_gt[0]))
    assert abs(err_deg) < 0.3 * traj.duration_s


def _heading_error_deg(traj) -> float:
    yaw = np.unwrap(np.arctan2(traj.poses[:, 1, 0], traj.poses[:, 0, 0]))
    yaw_gt = np.unwrap(np.arctan2(traj.ground_truth[:, 1, 0], traj.ground_truth[:, 0, 0]))
    return float(np.degrees((yaw[-1] - yaw[0]) - (yaw_gt[-1] - yaw_gt[0])))


def test_estimated_mounting_yaws_fix_the_doppler_heading_on_real_singapore_scene(reader):
    """scene-0916's Doppler fit loses 23 deg of heading in 20 s with the nominal calibration;
    refitted with the mounting yaws ours estimates on the scene it is within 6 deg (measured
    +22.9 and +5.2 deg)."""
    ours = run_odometry(reader, ["scene-0916"], progress=False)
    mounting = ours.calibration["mounting_yaw_error_deg"]
    nominal = run_odometry(reader, ["scene-0916"], method="doppler", progress=False)
    recal = OdometryConfig.model_validate({"mounting_yaw_deg": mounting})
    calibrated = run_odometry(reader, ["scene-0916"], recal, method="doppler", progress=False)
    assert _heading_error_deg(nominal) > 20
    assert abs(_heading_error_deg(calibrated)) < 0.3 * calibrated.duration_s


def test_scenes_of_two_cars_keep_their_own_calibration(reader, tmp_path):
    """A Boston and a Singapore scene in one run: the Boston car's mounting estimate does not
    carry into the Singapore car's scene, which runs as it does alone."""
    one = OdometryConfig.model_validate({"fusion": {"calibration": {"passes": 1}}})
    both = run_odometry(reader, ["scene-0103", "scene-0061"], one, progress=False)
    alone = run_odometry(reader, ["scene-0061"], one, progress=False)
    assert [c["scenes"] for c in both.calibrations] == [["scene-0103"], ["scene-0061"]]
    assert both.calibration == both.calibrations[1]
    np.testing.assert_array_equal(both.scene("scene-0061").poses, alone.poses)
    summary = write_outputs(both, tmp_path / "out", one)
    assert summary["doppler_calibration_by_rig"] == both.calibrations
    assert summary["doppler_calibration"]["rig"] == both.calibrations[1]["rig"]
