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


def test_removed_link_options_are_unknown_keys():
    """Confirmations of lone votes and weak votes are gone (never decisive on the calibrated
    world): an old config naming them fails on the key, not silently."""
    for key in ("loops.confirm_max_checks=0", "loops.weak_vote_min_tight_fitness=null"):
        with pytest.raises(ConfigError, match=key.split("=")[0].split(".")[1]):
            load_config(SlamConfig, None, [key])


def test_candidate_map_and_proximity_persistence_are_checked():
    with pytest.raises(ConfigError, match=r"key_frames.candidate_map"):
        load_config(SlamConfig, None, ["key_frames.candidate_map=future"])
    with pytest.raises(ConfigError, match=r"loops.proximity_min_neighbors"):
        load_config(SlamConfig, None, ["loops.proximity_min_neighbors=-1"])
    off = load_config(SlamConfig, None, ["loops.proximity_min_neighbors=null"])
    assert off.loops.proximity_min_neighbors is None
