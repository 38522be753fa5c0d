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


#: What slam/fast.yaml changes in slam/default.yaml.
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


def test_fast_slam_preset_differs_from_default_only_in_its_speed_keys():
    """slam/fast.yaml is slam/default.yaml with FAST_KEYS changed (its header says what they
    trade)."""
    fast = _leaves(load_config(SlamConfig, CONFIG_DIR / "slam" / "fast.yaml"))
    default = _leaves(load_config(SlamConfig, CONFIG_DIR / "slam" / "default.yaml"))
    changed = {k: v for k, v in fast.items() if default[k] != v}
    assert changed == FAST_KEYS
