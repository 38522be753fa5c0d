from pathlib import Path

import numpy as np
import pytest
from pr_synthetic import BASE_US, synthetic_frames

from radarslam.errors import DataError
from radarslam.place_recognition.config import SplitConfig
from radarslam.place_recognition.dataset import (
    DAY_US,
    PreparedData,
    build_sequences,
    edge_mask,
    greedy_database,
    heldout_mask,
    make_split,
)


def test_split_rules_pinned():
    pos, t, names = synthetic_frames()
    cfg = SplitConfig(split_day=5)
    s = make_split(pos, t, names, cfg)
    # greedy 1 m rule over the pool (edge frames excluded): x = 1.0, 2.5, 4.0 and 101, 102.5, 104
    assert s.splits["database"].tolist() == [2, 5, 8, 26, 29, 32]
    assert len(s.splits["train"]) == 8 + 8 + 8 - 6
    held = np.concatenate([s.splits["val"], s.splits["test"]])
    assert sorted(held.tolist()) == list(range(38, 46))  # s3 kept (8.5 m), s4 dropped (50 m)
    assert len(s.splits["val"]) == 2 and len(s.splits["test"]) == 6  # 1:4 of 8, rounded
    assert s.counts["heldout_dropped"] == 8 and s.counts["edge_excluded"] == 20
    # seeded: same split twice, another seed usually another val set
    again = make_split(pos, t, names, cfg)
    np.testing.assert_array_equal(again.splits["val"], s.splits["val"])
    assert not set(s.splits["train"]) & set(s.splits["database"])


def test_greedy_database_one_metre_rule():
    pos = np.array([[0, 0], [0.5, 0], [1.0, 0], [1.01, 0], [1.5, 0], [2.02, 0.0]])
    assert greedy_database(pos, np.arange(6), 1.0).tolist() == [0, 3, 5]
    # order matters: it is the candidates' order
    assert greedy_database(pos, np.arange(6)[::-1], 1.0).tolist() == [5, 3, 0]


def test_time_split_modes_and_edges():
    t = BASE_US + np.array([0, 1, 2, 3, 10, 11], np.int64) * DAY_US
    assert heldout_mask(t, SplitConfig(split_day=3)).tolist() == [0, 0, 0, 1, 1, 1]
    frac = SplitConfig(time_split="fraction", heldout_day_fraction=0.3)
    assert heldout_mask(t, frac).tolist() == [0, 0, 0, 0, 1, 1]  # ceil(0.3 * 6) = 2 days
    with pytest.raises(DataError, match="every day"):
        heldout_mask(t[:1], frac)
    names = np.array(["a"] * 5 + ["b"] * 3)
    assert edge_mask(names, 2).tolist() == [0, 0, 1, 0, 0, 0, 0, 0]
    seq = build_sequences(names, 3)
    assert seq[0].tolist() == [0, 0, 0] and seq[4].tolist() == [2, 3, 4]
    assert seq[6].tolist() == [5, 5, 6]  # clamped at the start of scene b
    with pytest.raises(DataError, match="contiguous"):
        build_sequences(np.array(["a", "b", "a"]), 2)


def test_positives_negatives_and_radii():
    pos, t, names = synthetic_frames()
    s = make_split(pos, t, names, SplitConfig(split_day=5))
    n = len(pos)
    data = PreparedData(
        root=Path("mem"),
        images=np.zeros((n, 4, 4), np.uint8),
        positions_xy=pos,
        yaw_rad=np.zeros(n),
        timestamps_us=t,
        scene_names=names,
        sample_tokens=np.array([f"tok{i}" for i in range(n)]),
        rcs=[np.zeros(0)] * n,
        sequences=s.sequences,
        splits=s.splits,
    )
    q = 38  # s3 at (1.0, 8.5): DB (1, 0) 8.5 m, (2.5, 0) 8.63 m, (4, 0) 9.01 m
    assert data.positives(q).tolist() == [2, 5]
    assert data.negatives_pool(q).tolist() == [26, 29, 32]  # > 18 m: only the far scene
    assert data.is_positive(np.array([q]), np.array([[2, 8]])).tolist() == [[True, False]]
    assert data.frames_float([q], seq_len=2).shape == (1, 2, 1, 4, 4)
    # driven the other way round: heading within the given error of the query's turned by pi
    data.yaw_rad[2], data.yaw_rad[5], data.yaw_rad[q] = 3.0, -2.2, -0.1
    assert data.reversed_positives(q, 45.0).tolist() == [2]  # 3.0: 2.4 deg off pi - 0.1
    assert data.reversed_positives(q, 60.0).tolist() == [2, 5]  # -2.2: 59.7 deg off
    assert data.reversed_positives(q, 2.0).tolist() == []


def test_split_errors():
    pos, t, names = synthetic_frames()
    with pytest.raises(DataError, match="held-out"):
        make_split(pos, t, names, SplitConfig(split_day=50))
    with pytest.raises(DataError, match="positions"):
        make_split(pos[:3], t, names, SplitConfig())


# ---------------------------------------------------------------------------------------------
# a prepared directory whose files disagree is refused


def _copy_prepared(src: Path, dst: Path) -> Path:
    import shutil

    return Path(shutil.copytree(src, dst / "mini"))


def _rewrite_npz(path: Path, **arrays) -> None:
    with np.load(path) as z:
        data = {k: z[k] for k in z.files}
    data.update(arrays)
    np.savez(path, **data)


def test_load_prepared_refuses_stale_or_damaged_stages(mini_prepared, tmp_path):
    from radarslam.place_recognition.dataset import load_prepared

    # a split made with another config (e.g. left over from an interrupted --overwrite)
    root = _copy_prepared(mini_prepared, tmp_path / "a")
    _rewrite_npz(root / "split.npz", config_hash=np.array("0123456789abcdef"))
    with pytest.raises(DataError, match=r"split\.npz: stale stage .*prepare --overwrite"):
        load_prepared(root)
    # same hash, but indices beyond the frames (a file copied from a larger cache)
    root = _copy_prepared(mini_prepared, tmp_path / "b")
    _rewrite_npz(root / "split.npz", test=np.array([3, 40]))
    with pytest.raises(DataError, match=r"split\.npz: 'test' indexes frames outside \[0, 16\)"):
        load_prepared(root)
    # a truncated stage file
    root = _copy_prepared(mini_prepared, tmp_path / "c")
    blob = (root / "images.npz").read_bytes()
    (root / "images.npz").write_bytes(blob[: len(blob) // 2])
    with pytest.raises(DataError, match=r"images\.npz: unreadable \(damaged or truncated"):
        load_prepared(root)


def test_split_summary_of_a_garbled_file(mini_prepared, tmp_path):
    from radarslam.place_recognition.dataset import split_summary

    root = _copy_prepared(mini_prepared, tmp_path)
    assert split_summary(root)["frames"] == 16
    (root / "split.json").write_bytes(b'{"database": 28, "tra\x01')
    with pytest.raises(DataError, match=r"split\.json: unreadable"):
        split_summary(root)
    (root / "split.json").write_text("[1, 2]")
    with pytest.raises(DataError, match=r"split\.json: expected a JSON object"):
        split_summary(root)
