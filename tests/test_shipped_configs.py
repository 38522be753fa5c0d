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
