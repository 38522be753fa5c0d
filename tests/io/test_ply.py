"""Binary PLY written without open3d reads back in open3d, laid out as open3d writes it."""

from __future__ import annotations

import numpy as np
import pytest

from radarslam.io.ply import write_ply_points


def _body(path):
    data = path.read_bytes()
    return data[data.index(b"end_header\n") + len(b"end_header\n") :]


@pytest.mark.parametrize("with_colors", [True, False])
def test_ply_matches_open3d(tmp_path, with_colors):
    o3d = pytest.importorskip("open3d")
    rng = np.random.default_rng(0)
    xyz = rng.normal(scale=100.0, size=(500, 3))
    colors = None
    if with_colors:
        colors = rng.uniform(-0.1, 1.1, size=(500, 3))
        colors[:4, 0] = [0.5 / 255, 1.5 / 255, 0.5, 254.49 / 255]  # rounding half up, as open3d
    write_ply_points(tmp_path / "ours.ply", xyz, colors)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    if with_colors:
        pc.colors = o3d.utility.Vector3dVector(np.clip(colors, 0, 1))
    assert o3d.io.write_point_cloud(str(tmp_path / "o3d.ply"), pc, write_ascii=False)
    assert _body(tmp_path / "ours.ply") == _body(tmp_path / "o3d.ply")
    back = o3d.io.read_point_cloud(str(tmp_path / "ours.ply"))
    np.testing.assert_array_equal(np.asarray(back.points), xyz)
    assert back.has_colors() == with_colors
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


def test_empty_cloud(tmp_path):
    write_ply_points(tmp_path / "e.ply", np.zeros((0, 3)))
    assert b"element vertex 0\n" in (tmp_path / "e.ply").read_bytes()
