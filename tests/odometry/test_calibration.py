"""Radar rigs and their Doppler calibration (radarslam.odometry.calibration)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from radarslam.odometry.calibration import (
    DopplerCalibration,
    find_rig,
    mounting_rotations,
    nominal_extrinsics,
    rig_id,
    same_rig,
    with_mounting,
)
from radarslam.types import RADAR_CHANNELS, RADAR_DTYPE, RadarFrame, RadarSweep


def _pose(x: float, yaw_deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    m[0, 3] = x
    return m


def test_rigs_are_told_apart_by_the_channels_they_share():
    car_a = nominal_extrinsics(
        {"RADAR_FRONT": _pose(3.4, 0.0), "RADAR_BACK_LEFT": _pose(-0.5, 174)}
    )
    car_b = nominal_extrinsics({"RADAR_FRONT": _pose(3.5, 0.0)})
    front_only = nominal_extrinsics({"RADAR_FRONT": _pose(3.4, 0.0)})
    left_only = nominal_extrinsics({"RADAR_FRONT_LEFT": _pose(2.4, 88.0)})
    # below the rounding (0.1 mm) two calibrations are one
    same_a = nominal_extrinsics({"RADAR_FRONT": _pose(3.4 + 2e-5, 0.0)})
    assert same_rig(car_a, front_only) and same_rig(car_a, same_a)
    assert not same_rig(car_a, car_b)
    assert not same_rig(car_a, left_only)  # nothing shared: no evidence either way
    known = [car_a, car_b]
    assert find_rig(known, front_only, current=None) == 0
    assert find_rig(known, car_b, current=0) == 1  # the current rig is contradicted
    assert find_rig(known, left_only, current=1) == 1  # nothing contradicts the current one
    assert find_rig(known, left_only, current=None) is None
    assert rig_id(car_a) == rig_id(dict(reversed(list(car_a.items()))))  # order-free
    assert rig_id(car_a) != rig_id(car_b) and len(rig_id(car_a)) == 8


def test_a_mounting_correction_turns_only_its_radar():
    sweeps = {
        ch: RadarSweep(ch, 1_000, np.zeros(0, RADAR_DTYPE), _pose(1.0, 10.0), np.eye(4))
        for ch in ("RADAR_FRONT", "RADAR_BACK_LEFT")
    }
    frame = RadarFrame(1_000, sweeps, np.eye(4))
    assert with_mounting(frame, {}) is frame
    turned = with_mounting(frame, mounting_rotations({"RADAR_BACK_LEFT": 0.5}))
    left = turned.sweeps["RADAR_BACK_LEFT"].ego_from_sensor
    assert math.degrees(math.atan2(left[1, 0], left[0, 0])) == pytest.approx(10.5)
    assert left[0, 3] == pytest.approx(1.0)  # turned about the sensor, not moved
    assert turned.sweeps["RADAR_FRONT"] is frame.sweeps["RADAR_FRONT"]


def test_the_mounting_calibration_is_reported_per_radar_in_degrees():
    rad = tuple(math.radians(0.1 * (i + 1)) for i in range(len(RADAR_CHANNELS)))
    cal = DopplerCalibration("mounting", rad, rad, 0.0, 0.0, -0.003, rig="abcd1234", scenes=("s",))
    out = cal.as_dict()
    assert out["mounting_yaw_error_deg"]["RADAR_FRONT"] == pytest.approx(0.1)
    assert out["mounting_yaw_sigma_deg"]["RADAR_BACK_RIGHT"] == pytest.approx(0.5)
    assert (out["rig"], out["scenes"], out["radar_speed_scale_error"]) == (
        "abcd1234",
        ["s"],
        -0.003,
    )
    rate = DopplerCalibration("per_metre", (math.radians(0.01),), (0.0,), 0.0, 0.0).as_dict()
    assert rate["yaw_bias_deg_per_100m"] == pytest.approx(1.0) and "rig" not in rate
    assert set(DopplerCalibration("none", (), (), 0.0, 0.0).as_dict()) == {
        "yaw_bias_model",
        "radar_speed_scale_error",
    }


def test_second_pass_applies_the_estimate_with_its_median_out_on_top_of_the_given_yaws():
    """No radar measurement observes a turn all radars share: the pass's estimate of a single
    knocked unit is applied as that unit's turn against the others (common_yaw: median), on
    top of what the config gives; "filter" applies it as estimated."""
    from radarslam.odometry.config import OdometryConfig
    from radarslam.odometry.run import second_pass

    estimate = {"RADAR_FRONT": -1.3, "RADAR_FRONT_LEFT": 1.1, "RADAR_FRONT_RIGHT": 1.0,
                "RADAR_BACK_LEFT": 1.2, "RADAR_BACK_RIGHT": 0.9}  # fmt: skip
    given = {"RADAR_BACK_LEFT": 0.5}
    cfg = OdometryConfig.model_validate({"mounting_yaw_deg": given})
    applied = second_pass(cfg, {"mounting_yaw_error_deg": estimate}).mounting_yaw_deg
    expected = {"RADAR_FRONT": -2.3, "RADAR_FRONT_LEFT": 0.1, "RADAR_FRONT_RIGHT": 0.0,
                "RADAR_BACK_LEFT": 0.7, "RADAR_BACK_RIGHT": -0.1}  # fmt: skip
    assert applied == pytest.approx(expected, abs=1e-12)
    zero = dict.fromkeys(estimate, 0.0)
    assert second_pass(cfg, None).mounting_yaw_deg == pytest.approx({**zero, **given})
    raw = OdometryConfig.model_validate(
        {"mounting_yaw_deg": given, "fusion": {"calibration": {"common_yaw": "filter"}}}
    )
    applied = second_pass(raw, {"mounting_yaw_error_deg": estimate}).mounting_yaw_deg
    assert applied == pytest.approx({**estimate, "RADAR_BACK_LEFT": 1.7}, abs=1e-12)
