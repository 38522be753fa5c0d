"""The SLAM preset's own checks (the shipped presets load in tests/test_shipped_configs.py)."""

import pytest

from radarslam.config import load_config
from radarslam.errors import ConfigError
from radarslam.slam.config import SlamConfig


@pytest.mark.parametrize("channel", ["RADAR_FRONT", "RADAR_BACK_LEFT"])
def test_key_frame_reference_is_a_radar_channel(channel):
    cfg = load_config(SlamConfig, None, [f"key_frames.ref_channel={channel}"])
    assert cfg.key_frames.ref_channel == channel


def test_unknown_key_frame_reference_fails_before_any_data_is_read():
    with pytest.raises(
        ConfigError, match=r"key_frames.ref_channel=RADAR_TOP.*unknown radar channel"
    ):
        load_config(SlamConfig, None, ["key_frames.ref_channel=RADAR_TOP"])
