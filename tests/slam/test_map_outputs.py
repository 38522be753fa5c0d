import numpy as np

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
