"""Synthetic key-frame positions shared by the split and evaluation tests, and the tiny model
configuration and learnable corridor data shared by the model, training and ablation tests."""

import numpy as np

from radarslam.place_recognition.dataset import DAY_US, PreparedData
from radarslam.place_recognition.models import ModelConfig

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


def corridor_data(
    seed: int = 0, n_db: int = 60, size: int = 32, step_m: float = 2.0, reversed_drives=False
):
    """Four drives along a 118 m corridor of random landmarks, seen as 32x32 occupancy at 1 m/px.

    The database drive samples every 2 m on the centre line; train / val / test drives are shifted
    along (0.5-1.5 m) and across (0.4-0.8 m) it, lose 25% of the landmarks per frame and gain 12
    clutter cells, so places must be recognised from partial, noisy, shifted views.
    ``reversed_drives``: two more drives, train and val queries, driven the other way round.
    """
    rng = np.random.default_rng(seed)
    half = size // 2
    length = (n_db - 1) * step_m
    landmarks = np.column_stack(
        [rng.uniform(-half - 4, length + half + 4, 700), rng.uniform(-half, half, 700)]
    )
    drives = [("db", 0.0, 0.0, n_db), ("train", 1.0, 0.4, n_db - 1)]
    drives += [("val", 0.5, -0.4, n_db - 1), ("test", 1.5, 0.8, n_db - 1)]
    if reversed_drives:
        drives += [("train_reversed", 1.0, -0.6, n_db - 1), ("val_reversed", 0.5, 0.6, n_db - 1)]
    images, positions, names = [], [], []
    for name, x0, y0, count in drives:
        turn = -1.0 if name.endswith("_reversed") else 1.0
        for k in range(count):
            x = x0 + k * step_m if turn > 0 else length - x0 - k * step_m
            rel = turn * (landmarks - (x, y0))
            rel = rel[rng.random(len(rel)) < 0.75]
            r = np.round(rel[:, 0]).astype(int) + half
            c = np.round(rel[:, 1]).astype(int) + half
            ok = (r >= 0) & (r < size) & (c >= 0) & (c < size)
            img = np.zeros((size, size), np.uint8)
            img[r[ok], c[ok]] = 1
            img[rng.integers(0, size, 12), rng.integers(0, size, 12)] = 1
            images.append(img)
            positions.append((x, y0))
            names.append(name)
    data = PreparedData.from_drives("synthetic-corridor", images, positions, names)
    if reversed_drives:
        names = np.asarray(names)
        reverse = np.char.endswith(names, "_reversed")
        data.yaw_rad[reverse] = np.pi
        for split in ("train", "val"):
            data.splits[split] = np.concatenate(
                [data.splits[split], np.flatnonzero(names == f"{split}_reversed")[2:]]
            )
    return data
