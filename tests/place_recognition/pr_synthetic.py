"""Synthetic key-frame positions shared by the split and evaluation tests, and the tiny model
configuration shared by the model and training tests."""

import numpy as np

from place_recognition.dataset import DAY_US
from place_recognition.models import ModelConfig

#: A 32x32, two-block SE+TE network: real code paths at test speed.
TINY = ModelConfig(
    preset="tiny",
    image_size_px=32,
    widths=[4, 8],
    convs_per_block=1,
    seq_len=3,
    use_temporal=True,
    descriptor_dim=16,
)

BASE_US = 1_532_400_000_000_000


def synthetic_frames():
    """Five scenes of 12 key frames 0.5 m apart along x (see the numbers pinned below)."""
    specs = [  # name, day, x0, y
        ("s1", 0, 0.0, 0.0),
        ("s2", 1, 0.0, 0.3),
        ("s0", 0, 100.0, 0.0),
        ("s3", 10, 0.0, 8.5),
        ("s4", 10, 0.0, 50.0),
    ]
    pos, t, names = [], [], []
    for name, day, x0, y in specs:
        for i in range(12):
            pos.append((x0 + 0.5 * i, y))
            t.append(BASE_US + day * DAY_US + i * 500_000 + (1_000_000 if name == "s0" else 0))
            names.append(name)
    return np.array(pos), np.array(t, np.int64), np.array(names)
