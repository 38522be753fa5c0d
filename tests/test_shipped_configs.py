"""The shipped YAML presets load under their strict models and say what the code's defaults are,
so a user reading radarslam/configs/ sees the values a run without --config uses."""

import pytest
from pydantic import BaseModel

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


#: What slam/fast.yaml changes in slam/synthetic.yaml.
FAST_KEYS = {
    "key_frames.min_travel_m": 0.2,
    "key_frames.max_interval_s": 1.0,
    "loops.proximity_max_range_m": 40.0,
}


def _leaves(value, prefix=""):
    """A config's leaf settings as {dotted key: value}."""
    if isinstance(value, BaseModel):
        out = {}
        for name in type(value).model_fields:
            out.update(_leaves(getattr(value, name), f"{prefix}{name}."))
        return out
    return {prefix.rstrip("."): value}


def test_fast_slam_preset_differs_from_synthetic_only_in_its_speed_keys():
    """slam/fast.yaml is slam/synthetic.yaml with FAST_KEYS changed (its header says what they
    trade)."""
    fast = _leaves(load_config(SlamConfig, CONFIG_DIR / "slam" / "fast.yaml"))
    synthetic = _leaves(load_config(SlamConfig, CONFIG_DIR / "slam" / "synthetic.yaml"))
    changed = {k: v for k, v in fast.items() if synthetic[k] != v}
    assert changed == FAST_KEYS
