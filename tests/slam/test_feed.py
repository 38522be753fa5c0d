"""The SLAM feed: which scenes continue the drive of the one before them."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from radarslam.slam.feed import drives_on
from radarslam.types import SceneInfo


def _scene(i: int) -> SceneInfo:
    return SceneInfo(f"scene-{i:04d}", f"t{i}", "log", "city", "2026-01-01", "car", 40, "a", "b")


@pytest.mark.parametrize(
    ("log", "gap_s", "continues"),
    [("log", 0.3, True), ("log", 1.0, True), ("log", 1.2, False), ("other", 0.3, False)],
)
def test_a_scene_drives_on_from_the_scene_before_it(log, gap_s, continues):
    """Same log and within the gap limit (1 s here) of the previous scene's last frame."""
    before, nxt = _scene(0), _scene(1)
    nxt = SceneInfo(nxt.name, nxt.token, log, "city", "2026-01-01", "car", 40, "a", "b")
    first = SimpleNamespace(timestamp_us=5_000_000 + round(gap_s * 1e6))
    assert drives_on(nxt, (before, 5_000_000), first, 1e6) is continues
    assert not drives_on(nxt, None, first, 1e6)  # nothing before it (or without frames)
    assert not drives_on(nxt, (before, 5_000_000), None, 1e6)  # no frame of its own
    # a start on the other's last frame (a shared boundary key frame) or a little before it
    # counts; one far before it is not a sequel
    for start_us, sequel in ((5_000_000, True), (4_500_000, True), (2_000_000, False)):
        start = SimpleNamespace(timestamp_us=start_us)
        assert drives_on(nxt, (before, 5_000_000), start, 1e6) is (sequel and log == "log")
    nolog = SceneInfo(nxt.name, nxt.token, "", "city", "2026-01-01", "car", 40, "a", "b")
    assert not drives_on(nolog, (_scene(0), 5_000_000), first, 1e6)
