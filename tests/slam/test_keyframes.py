"""Key-frame accumulation from buffered sweeps (radarslam.slam.keyframes)."""

from __future__ import annotations

import numpy as np
import pytest

from radarslam.slam.keyframes import SweepBuffer


@pytest.fixture(scope="module")
def frames(tiny_dataroot):
    from radarslam.nuscenes.reader import NuScenesRadar

    reader = NuScenesRadar(tiny_dataroot, "v1.0-mini")
    it = reader.iter_frames(reader.scenes()[0])
    return [next(it) for _ in range(8)]


def _fill(frames, masks_for=None):
    buf = SweepBuffer(nsweeps=7)
    for f in frames:
        masks = masks_for(f) if masks_for else None
        buf.add_frame(f, f.world_from_ego, np.zeros(3), masks)
    last = frames[-1]
    return buf.accumulate(last.timestamp_us, last.world_from_ego)


def test_static_masks_decide_which_points_enter_the_cloud(frames):
    everything = _fill(frames, lambda f: {ch: np.ones(len(s), bool) for ch, s in f.sweeps.items()})
    front_only = _fill(
        frames,
        lambda f: {ch: np.full(len(s), ch == "RADAR_FRONT") for ch, s in f.sweeps.items()},
    )
    assert len(everything.points) > len(front_only.points) > 0
    assert set(np.unique(front_only.points["channel"])) == {0}  # RADAR_CHANNELS index of FRONT
    # all-true masks remove nothing: the same cloud as no dynamic-point removal at all
    assert len(_fill(frames).points) == len(everything.points)


def test_a_mask_of_the_wrong_length_is_a_clear_error(frames):
    buf = SweepBuffer()
    f = frames[0]
    ch = next(iter(f.sweeps))
    with pytest.raises(ValueError, match=f"static mask of {ch}"):
        buf.add_frame(f, f.world_from_ego, np.zeros(3), {ch: np.ones(len(f.sweeps[ch]) + 1, bool)})
