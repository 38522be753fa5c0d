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


@pytest.mark.parametrize(
    "key",
    [
        # confirmations of lone votes and weak votes: never decisive on the calibrated world
        "loops.confirm_max_checks=0",
        "loops.weak_vote_min_tight_fitness=null",
        # past-only candidate maps for turned revisits, the turned search's back-off, the
        # travel gate on AutoPlace queries: no better, or worse, on the calibrated world
        "key_frames.candidate_map=centred",
        "loops.reversed_backoff_searches=8",
        "loops.recognition_min_travel_m=1",
        # a well-conditioned vote per link: no run needs it, seed 7 loses recall to it
        "loops.link_min_constraint_ratio=0.8",
        # clutter filter on proximity registrations: no run needs it, seed 21's map is worse
        "loops.proximity_min_neighbors=2",
        # the proximity search placed through the session's link instead of its latest loop:
        # the same maps on every run (within 0.03 m)
        "loops.proximity_origin=link",
    ],
)
def test_removed_options_are_unknown_keys(key):
    """An old config naming a removed option fails on the key, not silently."""
    with pytest.raises(ConfigError, match=key.split("=")[0].split(".")[1]):
        load_config(SlamConfig, None, [key])
