import numpy as np
import pytest

from radarslam.geometry import se2_to_matrix
from radarslam.slam.map import StaticMapBuilder, StaticMapConfig
from radarslam.slam.outputs import write_map_ply
from radarslam.types import ACCUMULATED_DTYPE


def _cloud(xy, v):
    pts = np.zeros(len(xy), dtype=ACCUMULATED_DTYPE)
    pts["x"], pts["y"] = xy[:, 0], xy[:, 1]
    pts["vx_comp"] = v
    pts["rcs"] = 5.0
    return pts


def test_static_map_removes_movers_and_uses_the_poses(tmp_path):
    wall = np.column_stack([np.linspace(0, 10, 21), np.full(21, 5.0)])
    b = StaticMapBuilder(StaticMapConfig(voxel_size_m=0.5, min_points_per_voxel=2))
    for k in range(3):
        pose = se2_to_matrix(k * 2.0, 0.0, 0.0)  # the wall seen from three places
        local = wall - [k * 2.0, 0.0]
        mover = np.array([[3.0, 1.0], [4.0, 1.0]])
        b.add(pose, _cloud(np.concatenate([local, mover]), np.r_[np.zeros(21), 8.0, 8.0]))
    m = b.build()
    assert b.num_dynamic_removed == 6
    assert np.allclose(m.xyz[:, 1], 5.0) and m.hits.min() >= 2
    assert len(m) == 21 and np.allclose(m.rcs, 5.0)
    # a lone clutter point is dropped by min_points_per_voxel
    b.add(np.eye(4), np.array([[50.0, 50.0]]))
    assert len(b.build()) == 21
    import open3d as o3d

    write_map_ply(tmp_path / "map.ply", m)
    back = o3d.io.read_point_cloud(str(tmp_path / "map.ply"))
    np.testing.assert_allclose(np.asarray(back.points), m.xyz, atol=1e-6)
    assert not list(tmp_path.glob(".*tmp*"))


# --- the results folder is written as a whole ----------------------------------------------------


def _sessions(*names):
    from radarslam.slam.outputs import SessionResult

    t = 1_000_000 + np.arange(5, dtype=np.int64) * 500_000
    poses = np.stack([se2_to_matrix(float(i), 0.0, 0.0) for i in range(5)])
    return [SessionResult(n, t, poses, poses, poses) for n in names]


def _snapshot(d):
    return {
        p.relative_to(d).as_posix(): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()
    }


def test_rewriting_a_results_folder_leaves_no_stale_file(tmp_path):
    from radarslam.slam.outputs import write_results

    out = tmp_path / "res"
    write_results(out, _sessions("scene-0001", "scene-0002"), loops=[], config_yaml="a: 1\n")
    (out / "metrics.json").write_text("{}")  # what eval adds
    (out / "plots").mkdir()
    (out / "plots" / "errors_scene-0002.png").write_bytes(b"png")
    write_results(out, _sessions("scene-0001"), loops=[], extra_json={"timing.json": {"s": 1}})
    assert sorted(p.name for p in out.iterdir()) == [
        "gt_scene-0001.kitti", "gt_scene-0001.tum", "loops.csv", "odometry_scene-0001.kitti",
        "odometry_scene-0001.tum", "poses_scene-0001.kitti", "poses_scene-0001.tum", "run.json",
        "timing.json",
    ]  # fmt: skip
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]  # no temporary folder
    assert (out.stat().st_mode & 0o777) == (0o777 & ~_umask())


def _umask():
    from radarslam.io.atomic import _umask

    return _umask()


@pytest.mark.parametrize("exc", [RuntimeError("disk on fire"), KeyboardInterrupt()])
def test_failure_inside_write_results_keeps_the_previous_folder(tmp_path, monkeypatch, exc):
    from radarslam.slam import outputs

    out = tmp_path / "res"
    outputs.write_results(out, _sessions("scene-0001", "scene-0002"), loops=[], config_yaml="a\n")
    before = _snapshot(out)

    def fail(*args, **kwargs):
        raise exc

    monkeypatch.setattr(outputs, "write_loops_csv", fail)  # after the trajectories are written
    with pytest.raises(type(exc)):
        outputs.write_results(out, _sessions("scene-0003"), loops=[], config_yaml="b\n")
    assert _snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]


def test_a_folder_holding_other_things_is_not_replaced(tmp_path):
    from radarslam.errors import DataError
    from radarslam.slam.outputs import check_results_dir, write_results

    out = tmp_path / "res"
    (out / "data").mkdir(parents=True)  # e.g. a dataroot
    with pytest.raises(DataError, match=r"res: holds 'data', which is not a result file"):
        write_results(out, _sessions("scene-0001"))
    (out / "run.json").write_text("{}")  # even in a results folder, sub-folders are not ours
    with pytest.raises(DataError, match=r"res: holds 'data'"):
        check_results_dir(out)
    assert sorted(p.name for p in out.iterdir()) == ["data", "run.json"]
    (out / "data").rmdir()
    (out / "notes.txt").write_text("mine")  # nor are a user's files beside the results
    with pytest.raises(DataError, match=r"res: holds 'notes.txt', which is not a result file"):
        write_results(out, _sessions("scene-0001"))
    assert (out / "notes.txt").read_text() == "mine"
    (tmp_path / "file").write_text("x")
    with pytest.raises(DataError, match=r"file: cannot create results folder \(.*is a file"):
        check_results_dir(tmp_path / "file")
    with pytest.raises(DataError, match=r"cannot create results folder \(.*file is a file"):
        check_results_dir(tmp_path / "file" / "res")
    assert (tmp_path / "file").read_text() == "x"


def test_write_errors_name_the_results_folder_not_the_temporary_one(tmp_path, monkeypatch):
    from radarslam.errors import DataError
    from radarslam.io import atomic
    from radarslam.slam.outputs import write_results

    def no_space(fd):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(atomic.os, "fsync", no_space)
    out = tmp_path / "res"
    with pytest.raises(DataError) as err:
        write_results(out, _sessions("scene-0001"))
    assert (
        str(err.value) == f"{out / 'poses_scene-0001.tum'}: cannot write (No space left on device)"
    )
    assert list(tmp_path.iterdir()) == []


def test_static_map_takes_an_empty_key_frame_cloud():
    builder = StaticMapBuilder()
    builder.add(np.eye(4), np.zeros(0, dtype=ACCUMULATED_DTYPE))  # every radar silent
    assert len(builder.build().xyz) == 0


def test_static_map_voxel_keys_never_overflow():
    # spans of ~1e9 voxels per axis: the scalar key (span product ~1e27) would wrap int64
    pts = np.array([[0.0, 0.0, 0.0], [1e6, 1e6, 1e6], [0.0, 1e6, 0.0], [1e6, 0.0, 0.0]])
    builder = StaticMapBuilder(StaticMapConfig(voxel_size_m=0.001, min_points_per_voxel=1))
    builder.add(np.eye(4), np.repeat(pts, 2, axis=0))
    m = builder.build()
    assert len(m) == 4 and set(m.hits.tolist()) == {2}
    np.testing.assert_allclose(np.sort(m.xyz, axis=0), np.sort(pts, axis=0))


def test_static_map_refuses_points_beyond_exact_voxel_indices():
    from radarslam.errors import DataError

    builder = StaticMapBuilder(StaticMapConfig(voxel_size_m=0.5))
    builder.add(np.eye(4), np.array([[1.0, 2.0, 0.0], [1e30, 2.0, 0.0]]))
    with pytest.raises(DataError, match=r"static map: point \[1e\+30, 2\.0, 0\.0\] m is too far"):
        builder.build()


def test_static_map_summed_chunk_by_chunk_is_the_map_of_all_points(monkeypatch):
    import radarslam.slam.map as map_module

    rng = np.random.default_rng(11)
    clouds = []
    for k in range(40):
        xy = rng.uniform(-20, 20, (int(rng.integers(0, 60)), 2))
        pts = _cloud(xy, rng.normal(0, 0.3, len(xy)))
        pts["rcs"] = np.where(rng.uniform(size=len(xy)) < 0.2, np.nan, rng.normal(5, 3, len(xy)))
        clouds.append((se2_to_matrix(0.3 * k, -0.1 * k, 0.02 * k), pts))

    def build(chunk_points):
        monkeypatch.setattr(map_module, "_CHUNK_POINTS", chunk_points)
        b = StaticMapBuilder(StaticMapConfig(voxel_size_m=1.0, min_points_per_voxel=2))
        for pose, pts in clouds:
            b.add(pose, pts)
        return b, b.build()

    one_go = build(10**9)[1]
    builder, chunked = build(37)
    assert builder._voxels is not None and len(one_go) > 50
    np.testing.assert_array_equal(chunked.hits, one_go.hits)
    np.testing.assert_allclose(chunked.xyz, one_go.xyz, rtol=0, atol=1e-12)
    np.testing.assert_allclose(chunked.rcs, one_go.rcs, rtol=0, atol=1e-12, equal_nan=True)
