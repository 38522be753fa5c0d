import numpy as np
import pytest

from radarslam.errors import DataError
from radarslam.geometry import make_transform, se2_to_matrix
from radarslam.io.trajectory import read_kitti, read_tum, write_kitti, write_tum


def _random_poses(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    poses = []
    for _ in range(n):
        q = rng.normal(size=4)
        t = rng.normal(scale=500.0, size=3) + np.array([1.2e3, 8.6e2, 0.0])
        poses.append(make_transform(t, q))
    return np.stack(poses)


def test_tum_round_trip_is_lossless(tmp_path):
    poses = _random_poses(20)
    ts = 1_532_402_927_647_951 + np.arange(20, dtype=np.int64) * 50_000 + 7
    path = tmp_path / "poses.tum"
    write_tum(path, ts, poses)
    ts2, poses2 = read_tum(path)
    assert ts2.dtype == np.int64
    np.testing.assert_array_equal(ts2, ts)
    np.testing.assert_allclose(poses2, poses, atol=1e-12)
    first = path.read_text().splitlines()[1].split()
    assert first[0] == "1532402927.647958"
    # quaternion scalar last (TUM / evo)
    assert len(first) == 8


def test_tum_matches_evo_reader(tmp_path):
    from evo.tools import file_interface

    poses = np.stack([se2_to_matrix(i * 1.5, np.sin(i), 0.1 * i) for i in range(10)])
    ts = np.arange(10, dtype=np.int64) * 500_000 + 1_000_000
    path = tmp_path / "a.tum"
    write_tum(path, ts, poses)
    traj = file_interface.read_tum_trajectory_file(str(path))
    np.testing.assert_allclose(traj.timestamps, ts / 1e6)
    np.testing.assert_allclose(np.stack(traj.poses_se3), poses, atol=1e-12)


def test_kitti_round_trip(tmp_path):
    poses = _random_poses(7, seed=3)
    path = tmp_path / "poses.txt"
    write_kitti(path, poses)
    lines = path.read_text().splitlines()
    assert len(lines) == 7 and all(len(line.split()) == 12 for line in lines)
    np.testing.assert_array_equal(read_kitti(path), poses)


def test_empty_trajectories(tmp_path):
    write_tum(tmp_path / "e.tum", np.zeros(0, dtype=np.int64), np.zeros((0, 4, 4)))
    ts, poses = read_tum(tmp_path / "e.tum")
    assert ts.shape == (0,) and poses.shape == (0, 4, 4)


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("1.0 0 0 0 0 0 0\n", r"bad\.tum:1: expected 8 values"),
        ("# c\n1.0 0 0 0 0 0 0 1\nx 0 0 0 0 0 0 1\n", r"bad\.tum:3: bad timestamp"),
        ("1.0 0 0 zz 0 0 0 1\n", r"bad\.tum:1: non-numeric"),
        ("1.0 0 0 nan 0 0 0 1\n", r"bad\.tum:1: non-finite"),
        ("1.0 0 0 0 0 0 0 0\n", r"bad\.tum:1: zero-norm quaternion"),
        (
            "1.0 0 0 0 0 0 0 1\n# c\n1.000000 1 0 0 0 0 0 1\n",
            r"bad\.tum:3: timestamp 1\.000000 repeats the previous one \(line 1\); timestamps must",
        ),
        (
            "1.0 0 0 0 0 0 0 1\n2.0 0 0 0 0 0 0 1\n1.5 0 0 0 0 0 0 1\n",
            r"bad\.tum:3: timestamp 1\.5 is earlier than the previous one \(line 2\)",
        ),
    ],
)
def test_malformed_tum_names_file_and_line(tmp_path, text, match):
    path = tmp_path / "bad.tum"
    path.write_text(text)
    with pytest.raises(DataError, match=match):
        read_tum(path)


def test_malformed_kitti(tmp_path):
    path = tmp_path / "bad.txt"
    path.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n1 0 0 0 0 1 0 0 0 0 1\n")
    with pytest.raises(DataError, match=r"bad\.txt:2: expected 12 values"):
        read_kitti(path)
    path.write_text("2 0 0 0 0 1 0 0 0 0 1 0\n")
    with pytest.raises(DataError, match=r"bad\.txt:1: rotation block"):
        read_kitti(path)
    with pytest.raises(DataError, match="does not exist"):
        read_kitti(tmp_path / "missing.txt")


def test_write_rejects_bad_input(tmp_path):
    with pytest.raises(DataError, match="shape"):
        write_tum(tmp_path / "x.tum", [0], np.eye(4))
    with pytest.raises(DataError, match="timestamps"):
        write_tum(tmp_path / "x.tum", [0, 1], np.stack([np.eye(4)]))
    bad = np.stack([np.eye(4)])
    bad[0, 0, 3] = np.inf
    with pytest.raises(DataError, match="pose 0 has non-finite"):
        write_kitti(tmp_path / "x.txt", bad)
    assert not (tmp_path / "x.txt").exists()


def test_binary_tum_is_a_data_error(tmp_path):
    path = tmp_path / "bin.tum"
    path.write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe" * 10)
    with pytest.raises(DataError, match=r"bin\.tum: not a UTF-8 text file \(a trajectory file"):
        read_tum(path)


def _se2_poses(n: int = 5) -> tuple[np.ndarray, np.ndarray]:
    ts = 1_533_152_744_702_540 + np.arange(n, dtype=np.int64) * 500_000
    poses = np.stack(
        [se2_to_matrix(1000.0 + 2 * i, 500.0 + 0.1 * i * i, 0.02 * i) for i in range(n)]
    )
    return ts, poses


@pytest.mark.parametrize(
    ("damage", "match"),
    [
        (lambda p: p @ np.diag([2.0, 2.0, 2.0, 1.0]), r"pose 0 has a non-orthonormal rotation"),
        (lambda p: p @ np.diag([1.0, 1.0, -1.0, 1.0]), r"pose 0 has a reflection .*det -1"),
        (
            lambda p: p + np.pad([[0, 0.5, 0], [0, 0, 0], [0, 0, 0]], ((0, 1), (0, 1))),
            r"pose 0 has a non-orthonormal rotation block \(scaled or skewed",
        ),
        (
            lambda p: np.concatenate(
                [p[:, :3], np.tile([[[1.0, 2.0, 3.0, 4.0]]], (len(p), 1, 1))], 1
            ),
            r"pose 0 has bottom row \[1\.0, 2\.0, 3\.0, 4\.0\], expected \[0, 0, 0, 1\]",
        ),
    ],
)
def test_writers_reject_poses_the_readers_would_reject(tmp_path, damage, match):
    ts, poses = _se2_poses()
    bad = damage(poses)
    with pytest.raises(DataError, match=r"x\.tum: " + match):
        write_tum(tmp_path / "x.tum", ts, bad)
    with pytest.raises(DataError, match=r"x\.kitti: " + match):
        write_kitti(tmp_path / "x.kitti", bad)
    assert not (tmp_path / "x.tum").exists() and not (tmp_path / "x.kitti").exists()


@pytest.mark.parametrize(
    ("stamps", "match"),
    [
        (lambda ts: ts[::-1], r"timestamp 1 \(\d+ us\) is earlier than the previous one"),
        (lambda ts: np.zeros(len(ts), dtype=np.int64), r"timestamp 1 \(0 us\) repeats the prev"),
        (
            lambda ts: np.ones(len(ts), dtype=bool),
            "timestamps_us must be integer microseconds, got bool",
        ),
        (lambda ts: ["a"] * len(ts), "timestamps_us must be .*got <U1 values such as 'a'"),
        (lambda ts: ts / 1e6, r"timestamp 0 is 1533152744\.70254; .*seconds given"),
        (lambda ts: np.full(len(ts), np.nan), "timestamp 0 is nan; timestamps_us must be finite"),
    ],
)
def test_write_tum_rejects_bad_timestamps(tmp_path, stamps, match):
    ts, poses = _se2_poses()
    with pytest.raises(DataError, match=r"x\.tum: " + match):
        write_tum(tmp_path / "x.tum", stamps(ts), poses)


def test_writers_convert_float32_and_lists_to_float64(tmp_path):
    ts, poses = _se2_poses()
    write_tum(tmp_path / "a.tum", ts.astype(float), poses.astype(np.float32))
    ts2, poses2 = read_tum(tmp_path / "a.tum")
    assert poses2.dtype == np.float64 and np.array_equal(ts2, ts)
    np.testing.assert_allclose(poses2, poses.astype(np.float32), atol=1e-9)
    write_kitti(tmp_path / "a.kitti", poses.tolist())
    assert np.array_equal(read_kitti(tmp_path / "a.kitti"), poses)
    with pytest.raises(DataError, match=r"a\.tum: poses must be a numeric \(N, 4, 4\) array"):
        write_tum(tmp_path / "a.tum", ts, [["a"]])


@pytest.mark.parametrize(
    ("stamp", "match"),
    [
        ("1e400", r"bad\.tum:1: timestamp '1e400' s is out of range"),
        ("9.3e12", r"bad\.tum:1: timestamp '9\.3e12' s is out of range"),
        ("-1e999999999", r"bad\.tum:1: timestamp '-1e999999999' s is out of range"),
        ("inf", r"bad\.tum:1: bad timestamp 'inf'"),
        ("1.5s", r"bad\.tum:1: bad timestamp '1\.5s'"),
    ],
)
def test_read_tum_timestamp_out_of_range_or_not_a_number(tmp_path, stamp, match):
    path = tmp_path / "bad.tum"
    path.write_text(f"{stamp} 0 0 0 0 0 0 1\n")
    with pytest.raises(DataError, match=match):
        read_tum(path)
    path.write_text("9.2e12 0 0 0 0 0 0 1\n")  # the largest order of magnitude int64 us holds
    assert read_tum(path)[0].tolist() == [9_200_000_000_000_000_000]


def test_kitti_rotations_printed_with_few_digits_are_reorthonormalised_once(tmp_path, caplog):
    import logging

    _, poses = _se2_poses()
    path = tmp_path / "few_digits.kitti"
    printed = poses.copy()
    printed[::7, :3, :3] *= 1.0015  # |R R^T - I| = 3e-3: beyond the strict 1e-3
    path.write_text(
        "".join(" ".join(f"{v:.6f}" for v in p[:3, :4].ravel()) + "\n" for p in printed)
    )
    with caplog.at_level(logging.WARNING, logger="radarslam.io"):
        read = read_kitti(path)
    assert len(caplog.records) == 1
    assert caplog.records[0].getMessage().startswith(f"{path}: ")
    assert "re-orthonormalised" in caplog.text
    r = read[::7, :3, :3]  # the blocks that were off; the others are as printed (1e-6)
    np.testing.assert_allclose(
        np.einsum("nij,nkj->nik", r, r), np.broadcast_to(np.eye(3), r.shape), atol=1e-12
    )
    np.testing.assert_allclose(read[:, :3, :3], poses[:, :3, :3], atol=1e-5)
    np.testing.assert_allclose(read[:, :3, 3], poses[:, :3, 3], atol=1e-3)
    # a block off by more than rounding is still refused, naming the line
    lines = path.read_text().splitlines()
    lines[3] = "1.05 0 0 0 0 1.05 0 0 0 0 1.05 0"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=r"few_digits\.kitti:4: rotation block is not a rotation"):
        read_kitti(path)
