"""The shipped YAML presets load under their strict models and say what the code's defaults are,
so a user reading radarslam/configs/ sees the values a run without --config uses."""

import pytest

from radarslam.config import CONFIG_DIR, load_config
from radarslam.eval.evaluate import EvalConfig
from radarslam.odometry.config import OdometryConfig
from radarslam.slam.backend_config import BackendConfig
from radarslam.slam.config import SlamConfig


@pytest.mark.parametrize(
    ("relative", "model"),
    [
        ("slam/default.yaml", SlamConfig),
        ("slam/backend.yaml", BackendConfig),
        ("odometry/default.yaml", OdometryConfig),
        ("eval/default.yaml", EvalConfig),
    ],
)
def test_shipped_preset_equals_the_model_defaults(relative, model):
    assert load_config(model, CONFIG_DIR / relative) == model()


def test_synthetic_slam_preset_turns_off_only_the_real_radar_terms():
    """slam/synthetic.yaml is slam/default.yaml with the odometry's mounting-yaw states and
    twist floor off (the simulator has exact calibrations and a clean Doppler)."""
    synthetic = load_config(SlamConfig, CONFIG_DIR / "slam" / "synthetic.yaml")
    default = SlamConfig()
    assert synthetic.odometry.fusion.calibration.yaw_bias_model == "none"
    assert synthetic.odometry.fusion.twist_sigma_floor == (0.0, 0.0, 0.0)
    fusion = synthetic.odometry.fusion.model_copy(
        update={
            "calibration": default.odometry.fusion.calibration,
            "twist_sigma_floor": default.odometry.fusion.twist_sigma_floor,
        }
    )
    assert fusion == default.odometry.fusion
    rest = {"odometry": default.odometry}
    assert synthetic.model_copy(update=rest) == default
