import re

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
    with pytest.raises(ValueError, match="is zero"):
        g.quat_to_rotation([0, 0, 0, 0])


@pytest.mark.parametrize("scale", [1e-8, 0.05, 20.0, 1e300])
def test_quaternions_far_from_unit_are_refused_like_the_tables_do(scale):
    q = np.array([np.cos(0.3), 0.0, 0.0, np.sin(0.3)]) * scale
    assert not g.quat_norms_ok(g.quat_norms(q))
    with pytest.raises(ValueError, match="not a rotation"):
        g.quat_to_rotation(q)


def test_quaternions_the_tables_accept_are_normalised():
    q = np.array([np.cos(0.3), 0.0, 0.0, np.sin(0.3)])
    for scale in (g.QUAT_NORM_MIN, 0.5, 3.0, g.QUAT_NORM_MAX):
        assert g.quat_norms_ok(g.quat_norms(q * scale))
        np.testing.assert_allclose(g.quat_to_rotation(q * scale), g.quat_to_rotation(q), atol=1e-12)


def test_invert_and_compose():
    a_from_b = g.make_transform([1, 2, 3], [np.cos(0.3), 0.1, 0.2, np.sin(0.3)])
    assert np.allclose(a_from_b @ g.invert(a_from_b), np.eye(4), atol=1e-12)


def test_se2_round_trip():
    pose = g.se2_to_matrix(3.0, -2.0, 2.5)
    assert np.allclose(g.matrix_to_se2(pose), [3.0, -2.0, 2.5])
    assert np.allclose(pose[:2, 3] + pose[:2, :2] @ [1.0, 0.0], [3 + np.cos(2.5), -2 + np.sin(2.5)])


def test_yaw_and_planar_rotation_helpers():
    yaws = np.array([-3.0, -0.4, 0.0, 1.2, 3.1])
    poses = np.stack([g.se2_to_matrix(1.0, 2.0, y) for y in yaws])
    assert np.allclose(g.yaws_of(poses), yaws)
    assert g.yaws_of(poses).tolist() == [g.yaw_of(p) for p in poses]
    assert g.yaws_of(poses[:, :2, :2]).tolist() == g.yaws_of(poses).tolist()
    for y in yaws:
        r = g.rot2(y)
        assert np.array_equal(r, g.se2_to_matrix(0.0, 0.0, y)[:2, :2])
        assert g.yaw_of(r) == pytest.approx(y)
        assert np.array_equal(g.rot2(-y), r.T)


def test_repair_rotations_repairs_drifted_rotation():
    pose = g.se2_to_matrix(1, 2, 0.7)
    pose[:3, :3] *= 1.003
    pose[0, 1] += 0.002
    repair = g.repair_rotations(pose[None])
    assert repair.count == 1 and 0 < repair.worst <= g.REPAIR_TOLERANCE
    fixed = repair.poses[0]
    r = fixed[:3, :3]
    assert np.allclose(r @ r.T, np.eye(3), atol=1e-12)
    assert np.allclose(fixed[:3, 3], [1, 2, 0])
    assert abs(g.yaw_of(fixed) - 0.7) < 0.02


def test_wrap_angle():
    assert np.allclose(g.wrap_angle([3 * np.pi, -3 * np.pi / 2, 0.1]), [np.pi, np.pi / 2, 0.1])


def _rigid(yaw=0.4, t=(1000.0, -20.0, 1.5)):
    pose = g.se2_to_matrix(t[0], t[1], yaw)
    pose[2, 3] = t[2]
    return pose


@pytest.mark.parametrize(
    ("damage", "match"),
    [
        (lambda p: np.full((4, 4), np.nan), "has non-finite entries"),
        (lambda p: p[:3, :3], r"has shape \(3, 3\), expected \(4, 4\)"),
        (lambda p: p @ np.diag([2.0, 2.0, 2.0, 1.0]), r"non-orthonormal .*R R\^T - I\| = 3"),
        (lambda p: p @ np.diag([1.0, 1.0, -1.0, 1.0]), r"reflection .*det -1"),
        (lambda p: p + np.pad([[0, 0.5, 0], [0, 0, 0], [0, 0, 0]], ((0, 1), (0, 1))), "skewed"),
        (lambda p: np.vstack([p[:3], [0.0, 0.0, 1.0, 1.0]]), r"bottom row \[0\.0, 0\.0, 1\.0"),
        (lambda p: [["a"]], "not a numeric 4x4 matrix"),
    ],
)
def test_rigid_problem_names_what_is_wrong(damage, match):
    bad = damage(_rigid())
    why = g.rigid_problem(bad)
    assert why is not None and re.search(match, why), why
    stack = np.stack([_rigid(), _rigid(0.1)])
    if np.shape(bad) == (4, 4) and np.asarray(bad).dtype != object:
        stack = np.stack([_rigid(), np.asarray(bad, dtype=float), _rigid(0.1)])
        assert g.rigid_problems(stack) == (1, why)


def test_rigid_problem_accepts_rigid_float32_and_lists():
    pose = _rigid()
    pose[:3, :3] = g.quat_to_rotation([0.9, 0.1, -0.2, 0.3])  # roll/pitch too
    assert g.rigid_problem(pose) is None
    assert g.rigid_problem(pose.astype(np.float32)) is None  # float32 rounding < 1e-6
    assert g.rigid_problem(pose.tolist()) is None
    assert g.rigid_problems(np.stack([pose] * 3)) is None
    assert g.rigid_problems(np.zeros((0, 4, 4))) is None
    almost = pose.copy()
    almost[:3, :3] *= 1 + 5e-4
    assert g.rigid_problem(almost) is not None and g.rigid_problem(almost, tol=2e-3) is None
