"""Descriptor passes: the turned images AutoPlace's turned search queries."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from pr_synthetic import TINY, corridor_data

from radarslam.place_recognition.config import ImageConfig
from radarslam.place_recognition.descriptors import FrameStore, compute_descriptors, turn_images
from radarslam.place_recognition.image import normalise_rcs, rasterise
from radarslam.place_recognition.models import build_model


@pytest.mark.parametrize(
    "cfg",
    [
        ImageConfig(),
        ImageConfig(size_px=21, resolution_m=2.0, crop_m=30.0, extra_channels=["count", "rcs"]),
    ],
)
def test_turned_image_is_the_image_of_the_turned_points(cfg):
    rng = np.random.default_rng(3)
    xy = rng.uniform(-1.2 * cfg.crop_m, 1.2 * cfg.crop_m, (4000, 2))
    rcs01 = normalise_rcs(rng.normal(5.0, 8.0, len(xy)))
    image = torch.from_numpy(rasterise(xy, cfg, rcs01))
    want = rasterise(-xy, cfg, rcs01)
    got = turn_images(image[None])[0].numpy()
    assert want[0].mean() > 0.05
    # an even image is mirrored about its centre pixel: its first row and column, which the
    # turned points fill, have no counterpart in the original image and stay empty
    edge = 1 - cfg.size_px % 2
    assert not got[:, :edge].any() and not got[:, :, :edge].any()
    assert np.array_equal(got[:, edge:, edge:], want[:, edge:, edge:])
    twice = turn_images(turn_images(image)).numpy()
    assert np.array_equal(twice[:, edge:, edge:], image.numpy()[:, edge:, edge:])


def test_turned_descriptors_describe_the_turned_sequences():
    data = corridor_data()
    torch.manual_seed(0)
    model = build_model(TINY)
    frames = data.splits["val"][:5]
    got = compute_descriptors(model, data, frames, turned=True)
    seqs = torch.from_numpy(data.images[data.sequences[frames]]).float()[:, :, None]
    with torch.no_grad():
        want = model(turn_images(seqs)).numpy()
    assert np.allclose(got, want, atol=1e-5)
    assert not np.allclose(got, compute_descriptors(model, data, frames), atol=1e-2)
    store = FrameStore(data.images, torch.device("cpu"), TINY)
    assert torch.equal(store.get(frames, turned=True), turn_images(store.get(frames)))
