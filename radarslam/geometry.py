"""Small rigid-transform helpers. Poses are 4x4 float64 matrices named ``a_from_b``.

``a_from_b @ p_b = p_a``. Quaternions follow nuScenes: (w, x, y, z).
"""

from __future__ import annotations

import math

import numpy as np


def quat_to_rotation(q_wxyz) -> np.ndarray:
    """3x3 rotation matrix from a (w, x, y, z) quaternion (normalised here)."""
    # Python floats: numpy scalar arithmetic costs ~10x more (one call per sweep read).
    w, x, y, z = np.asarray(q_wxyz, dtype=np.float64).tolist()
    n = w * w + x * x + y * y + z * z
    if not math.isfinite(n) or n < 1e-12:
        raise ValueError(f"quaternion {list(q_wxyz)} has zero or non-finite norm")
    s = 2.0 / n
    return np.array(
        [
            [1 - s * (y * y + z * z), s * (x * y - z * w), s * (x * z + y * w)],
            [s * (x * y + z * w), 1 - s * (x * x + z * z), s * (y * z - x * w)],
            [s * (x * z - y * w), s * (y * z + x * w), 1 - s * (x * x + y * y)],
        ]
    )


def rotation_to_quat(rotation: np.ndarray) -> np.ndarray:
    """(w, x, y, z) quaternion with w >= 0 from a 3x3 rotation matrix."""
    m = np.asarray(rotation, dtype=np.float64)
    t = np.trace(m)
    if t > 0:
        s = np.sqrt(t + 1.0) * 2
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    elif m[0, 0] > m[1, 1] and m[0, 0] > m[2, 2]:
        s = np.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = [(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s]
    elif m[1, 1] > m[2, 2]:
        s = np.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = [(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s]
    else:
        s = np.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = [(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s]
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return q if q[0] >= 0 else -q


def make_transform(translation, q_wxyz) -> np.ndarray:
    """4x4 pose from a translation (3,) and a (w, x, y, z) quaternion."""
    pose = np.eye(4)
    pose[:3, :3] = quat_to_rotation(q_wxyz)
    pose[:3, 3] = np.asarray(translation, dtype=np.float64)
    return pose


def invert(pose: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform (no general matrix inverse)."""
    inv = np.eye(4)
    r = pose[:3, :3]
    inv[:3, :3] = r.T
    inv[:3, 3] = -r.T @ pose[:3, 3]
    return inv


def se2_to_matrix(x: float, y: float, yaw: float) -> np.ndarray:
    """4x4 pose of a planar (x, y, yaw) motion."""
    # math and one np.array: called ~20 times per odometry frame, np.eye + slicing cost 3x more
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array(
        [[c, -s, 0.0, float(x)], [s, c, 0.0, float(y)], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]]
    )


def matrix_to_se2(pose: np.ndarray) -> np.ndarray:
    """(x, y, yaw) of a 4x4 pose projected on the ground plane."""
    return np.array([pose[0, 3], pose[1, 3], np.arctan2(pose[1, 0], pose[0, 0])])


def yaw_of(pose: np.ndarray) -> float:
    return float(np.arctan2(pose[1, 0], pose[0, 0]))


def transform_points(a_from_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Apply a 4x4 transform to (N, 3) points (or (N, 2), taken at z = 0)."""
    pts = np.asarray(points_b, dtype=np.float64)
    if pts.shape[1] == 2:
        pts = np.column_stack([pts, np.zeros(len(pts))])
    return pts @ a_from_b[:3, :3].T + a_from_b[:3, 3]


def rotate_vectors(a_from_b: np.ndarray, vectors_b: np.ndarray) -> np.ndarray:
    """Rotate (N, 2) or (N, 3) free vectors (velocities): rotation only, no translation."""
    v = np.asarray(vectors_b, dtype=np.float64)
    if v.shape[1] == 2:
        return v @ a_from_b[:2, :2].T
    return v @ a_from_b[:3, :3].T


def orthonormalize(pose: np.ndarray) -> np.ndarray:
    """Project the rotation block back onto SO(3) (SVD), keeping the translation."""
    out = np.array(pose, dtype=np.float64, copy=True)
    u, _, vt = np.linalg.svd(out[:3, :3])
    r = u @ vt
    if np.linalg.det(r) < 0:
        u[:, -1] *= -1
        r = u @ vt
    out[:3, :3] = r
    out[3] = [0, 0, 0, 1]
    return out


def wrap_angle(a):
    """Wrap angle(s) to (-pi, pi]."""
    return np.pi - (np.pi - np.asarray(a)) % (2 * np.pi)
