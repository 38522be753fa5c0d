import numpy as np
import pytest

from radarslam import geometry as g


def test_quaternion_round_trip_and_nuscenes_order():
    rng = np.random.default_rng(0)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = q if q[0] >= 0 else -q
        r = g.quat_to_rotation(q)
        assert np.allclose(r @ r.T, np.eye(3), atol=1e-12)
        assert np.isclose(np.linalg.det(r), 1.0)
        assert np.allclose(g.rotation_to_quat(r), q, atol=1e-9)
    # (w, x, y, z): a 90 deg yaw maps x onto y
    q_yaw90 = [np.cos(np.pi / 4), 0, 0, np.sin(np.pi / 4)]
    assert np.allclose(g.quat_to_rotation(q_yaw90) @ [1, 0, 0], [0, 1, 0])


def test_zero_quaternion_is_a_clear_error():
    with pytest.raises(ValueError, match="zero or non-finite"):
        g.quat_to_rotation([0, 0, 0, 0])


def test_invert_and_compose():
    a_from_b = g.make_transform([1, 2, 3], [np.cos(0.3), 0.1, 0.2, np.sin(0.3)])
    assert np.allclose(a_from_b @ g.invert(a_from_b), np.eye(4), atol=1e-12)


def test_se2_round_trip_and_points():
    pose = g.se2_to_matrix(3.0, -2.0, 2.5)
    assert np.allclose(g.matrix_to_se2(pose), [3.0, -2.0, 2.5])
    pts = g.transform_points(pose, np.array([[1.0, 0.0]]))
    assert np.allclose(pts, [[3 + np.cos(2.5), -2 + np.sin(2.5), 0.0]])
    v = g.rotate_vectors(pose, np.array([[1.0, 0.0]]))
    assert np.allclose(v, [[np.cos(2.5), np.sin(2.5)]])


def test_orthonormalize_repairs_drifted_rotation():
    pose = g.se2_to_matrix(1, 2, 0.7)
    pose[:3, :3] *= 1.01
    pose[0, 1] += 0.02
    fixed = g.orthonormalize(pose)
    r = fixed[:3, :3]
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.allclose(fixed[:3, 3], [1, 2, 0])
    assert abs(g.yaw_of(fixed) - 0.7) < 0.02


def test_wrap_angle():
    assert np.allclose(g.wrap_angle([3 * np.pi, -3 * np.pi / 2, 0.1]), [np.pi, np.pi / 2, 0.1])
