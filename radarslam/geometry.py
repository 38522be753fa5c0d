"""Small rigid-transform helpers. Poses are 4x4 float64 matrices named ``a_from_b``.

``a_from_b @ p_b = p_a``. Quaternions follow nuScenes: (w, x, y, z).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Norms of a (w, x, y, z) rotation quaternion that are normalised: a writer that did not
#: normalise, or printed few decimals, is off by far less than a factor 10; a norm outside these
#: bounds (a quaternion scaled by 1e-8, say) is a corrupt value, not a rotation.
QUAT_NORM_MIN = 0.1
QUAT_NORM_MAX = 10.0
_N2_MIN, _N2_MAX = (QUAT_NORM_MIN * (1 - 1e-9)) ** 2, (QUAT_NORM_MAX * (1 + 1e-9)) ** 2


def quat_norms(quats) -> np.ndarray:
    """Norms of (..., 4) quaternions without overflow (1e300 components give 1e300, not inf)."""
    return np.hypot.reduce(np.asarray(quats, dtype=np.float64), axis=-1)


def quat_norms_ok(norms) -> np.ndarray:
    """Which quaternion norms are accepted (and normalised): the rule of
    :func:`quat_to_rotation`, vectorised for the table readers. NaN is refused."""
    n = np.asarray(norms, dtype=np.float64)
    return (n >= QUAT_NORM_MIN) & (n <= QUAT_NORM_MAX)


def quat_norm_problem(norm: float) -> str | None:
    """Why a rotation quaternion of this norm is refused, as a phrase to follow "quaternion
    ...", or ``None`` when :func:`quat_norms_ok` accepts it."""
    if QUAT_NORM_MIN <= norm <= QUAT_NORM_MAX:
        return None
    if math.isnan(norm):
        return "has non-finite values"
    if norm == 0.0:
        return "is zero"
    return (
        f"has norm {norm:.3g}, not a rotation (a quaternion is normalised when its norm lies in "
        f"[{QUAT_NORM_MIN:g}, {QUAT_NORM_MAX:g}])"
    )


def quat_to_rotation(q_wxyz) -> np.ndarray:
    """3x3 rotation matrix from a (w, x, y, z) quaternion (normalised here); ValueError when
    :func:`quat_norm_problem` refuses its norm."""
    # Python floats: numpy scalar arithmetic costs ~10x more (one call per sweep read).
    w, x, y, z = np.asarray(q_wxyz, dtype=np.float64).tolist()
    n = w * w + x * x + y * y + z * z
    # a hair wider than quat_norms_ok: a norm the tables accepted (computed in another order)
    # must not fail here by a rounding
    if not _N2_MIN <= n <= _N2_MAX:  # NaN fails too
        why = quat_norm_problem(math.hypot(w, x, y, z))
        raise ValueError(f"quaternion {list(q_wxyz)} {why or 'has a norm at the accepted limit'}")
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
    qa = np.asarray(q)
    qa /= np.linalg.norm(qa)
    return qa if qa[0] >= 0 else -qa


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
    return np.array([pose[0, 3], pose[1, 3], yaw_of(pose)])


def yaw_of(pose: np.ndarray) -> float:
    """Heading (rad, in [-pi, pi]) of a pose or rotation matrix (4x4, 3x3 or 2x2): the angle of
    its x axis in the ground plane."""
    return float(np.arctan2(pose[1, 0], pose[0, 0]))


def yaws_of(poses: np.ndarray) -> np.ndarray:
    """:func:`yaw_of` of each of (..., n, n) poses or rotation matrices."""
    poses = np.asarray(poses)
    return np.arctan2(poses[..., 1, 0], poses[..., 0, 0])


def rot2(yaw: float) -> np.ndarray:
    """2x2 rotation by ``yaw`` (rad): ``rot2(yaw) @ p`` turns ``p`` counter-clockwise."""
    # math on a Python float: numpy's scalar functions cost ~10x more
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s], [s, c]])


_F64 = np.dtype(np.float64)
#: Default tolerance of :func:`rigid_problem` on ``R R^T - I``, ``det R - 1`` and the bottom row.
RIGID_TOLERANCE = 1e-6


def rigid_problem(pose, tol: float = RIGID_TOLERANCE) -> str | None:
    """Why ``pose`` is not a rigid 4x4 transform, or ``None`` when it is: shape (4, 4), finite
    entries, bottom row (0, 0, 0, 1) and a rotation block with ``|R R^T - I| <= tol`` and
    ``|det R - 1| <= tol``. The reason is a phrase to follow the pose's name in a message.

    Plain Python on the 16 numbers (~3 us): numpy's per-call overhead costs ~10x on a 4x4, and
    this runs once per odometry frame."""
    if type(pose) is not np.ndarray or pose.dtype is not _F64:
        try:
            pose = np.asarray(pose, dtype=np.float64)
        except (TypeError, ValueError):
            return f"is not a numeric 4x4 matrix (got {type(pose).__name__})"
    if pose.shape != (4, 4):
        return f"has shape {pose.shape}, expected (4, 4)"
    flat = pose.ravel().tolist()
    a0, a1, a2, a3, b0, b1, b2, b3, c0, c1, c2, c3, d0, d1, d2, d3 = flat
    gram = (
        a0 * a0 + a1 * a1 + a2 * a2 - 1.0,
        b0 * b0 + b1 * b1 + b2 * b2 - 1.0,
        c0 * c0 + c1 * c1 + c2 * c2 - 1.0,
        a0 * b0 + a1 * b1 + a2 * b2,
        a0 * c0 + a1 * c1 + a2 * c2,
        b0 * c0 + b1 * c1 + b2 * c2,
    )
    det = a0 * (b1 * c2 - b2 * c1) - a1 * (b0 * c2 - b2 * c0) + a2 * (b0 * c1 - b1 * c0)
    # Fast path: a sum of absolute deviations (NaN-propagating, >= their max) within tol.
    dev = sum(map(abs, gram)) + abs(det - 1.0) + abs(d0) + abs(d1) + abs(d2) + abs(d3 - 1.0)
    if dev <= tol and math.isfinite(a3) and math.isfinite(b3) and math.isfinite(c3):
        return None
    if not all(map(math.isfinite, flat)):
        return "has non-finite entries"
    if max(abs(d0), abs(d1), abs(d2), abs(d3 - 1.0)) > tol:
        return f"has bottom row {[d0, d1, d2, d3]}, expected [0, 0, 0, 1]"
    if det < 0:
        return f"has a reflection as rotation block (det {det:.6g}), not a rotation"
    orth = max(map(abs, gram))
    if orth > tol or abs(det - 1.0) > tol:
        return (
            f"has a non-orthonormal rotation block (scaled or skewed: max |R R^T - I| = "
            f"{orth:.3g}, det {det:.6g}; tolerance {tol:g})"
        )
    return None


def _rigid_deviations(arr: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per pose of an (N, 4, 4) stack: (max |R R^T - I|, det R, max bottom-row deviation,
    all entries finite)."""
    with np.errstate(invalid="ignore", over="ignore"):
        r = arr[:, :3, :3]
        gram = np.einsum("nij,nkj->nik", r, r)
        gram[:, [0, 1, 2], [0, 1, 2]] -= 1.0
        orth = np.abs(gram).max(axis=(1, 2))
        det = np.einsum("ni,ni->n", r[:, 0], np.cross(r[:, 1], r[:, 2]))
        bottom = np.abs(arr[:, 3] - (0.0, 0.0, 0.0, 1.0)).max(axis=1)
    return orth, det, bottom, np.isfinite(arr).all(axis=(1, 2))


def _stack(poses) -> np.ndarray:
    arr = np.asarray(poses, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise ValueError(f"expected (N, 4, 4) poses, got shape {arr.shape}")
    return arr


def rigid_problems(poses: np.ndarray, tol: float = RIGID_TOLERANCE) -> tuple[int, str] | None:
    """:func:`rigid_problem` of an (N, 4, 4) float64 stack, vectorised: ``(index, reason)`` of
    the first pose that is not rigid, or ``None``."""
    arr = _stack(poses)
    if len(arr) == 0:
        return None
    orth, det, bottom, finite = _rigid_deviations(arr)
    with np.errstate(invalid="ignore"):
        ok = (orth <= tol) & (np.abs(det - 1.0) <= tol) & (bottom <= tol) & finite
    if ok.all():
        return None
    i = int(np.argmin(ok))
    return i, rigid_problem(arr[i], tol) or "is not a rigid transform"


#: How far a rotation block may be from orthonormal (max |R R^T - I| and |det R - 1|) and still be
#: read as a rotation printed with few digits, then re-orthonormalised: KITTI files printed with 6
#: decimals, or poses that went through float32, are off by up to ~1e-3; a block off by more is
#: scaled or skewed, not rounded.
REPAIR_TOLERANCE = 0.01


@dataclass(frozen=True)
class RotationRepair:
    """What :func:`repair_rotations` did: the poses (a copy where any was repaired), how many
    rotation blocks it re-orthonormalised and the largest deviation among them."""

    poses: np.ndarray
    count: int = 0
    worst: float = 0.0


def repair_rotations(
    poses, tol: float = RIGID_TOLERANCE, repair_tol: float = REPAIR_TOLERANCE
) -> RotationRepair:
    """Re-orthonormalise (SVD) the rotation blocks of an (N, 4, 4) stack that deviate from a
    rotation by more than ``tol`` but at most ``repair_tol``; ``ValueError((index, reason))``
    naming the first pose beyond repair (non-finite, bottom row off by more than ``tol``, a
    reflection, or a block deviating by more than ``repair_tol``)."""
    arr = _stack(poses)
    if len(arr) == 0:
        return RotationRepair(arr)
    orth, det, bottom, finite = _rigid_deviations(arr)
    with np.errstate(invalid="ignore"):
        dev = np.maximum(orth, np.abs(det - 1.0))
        rigid = (dev <= tol) & (bottom <= tol) & finite
        fixable = finite & (bottom <= tol) & (det > 0) & (dev <= repair_tol)
    if rigid.all():
        return RotationRepair(arr)
    if not (rigid | fixable).all():
        i = int(np.argmin(rigid | fixable))
        raise ValueError(i, rigid_problem(arr[i], repair_tol) or "is not a rigid transform")
    idx = np.flatnonzero(~rigid)
    out = arr.copy()
    u, _, vt = np.linalg.svd(out[idx, :3, :3])
    out[idx, :3, :3] = u @ vt  # det(u vt) = +1: det R > 0 and R is near a rotation
    out[idx, 3] = (0.0, 0.0, 0.0, 1.0)
    return RotationRepair(out, len(idx), float(dev[idx].max()))


def wrap_angle(a):
    """Wrap angle(s) to (-pi, pi]."""
    return np.pi - (np.pi - np.asarray(a)) % (2 * np.pi)
