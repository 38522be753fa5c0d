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
    with pytest.raises(DataError, match=r"bin\.tum: not a text trajectory file"):
        read_tum(path)
