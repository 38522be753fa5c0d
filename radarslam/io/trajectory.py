"""Trajectory files: TUM (evo's ``tum`` format) and KITTI odometry format, written atomically.

TUM: one pose per line ``timestamp_s tx ty tz qx qy qz qw`` (seconds, quaternion scalar LAST),
``#`` comment lines allowed. Timestamps are integer microseconds in memory and are written as exact
decimal seconds with six fractional digits, so a round trip is lossless.

KITTI: one pose per line, the 12 numbers of the top 3x4 block of ``world_from_ego`` row-major, no
timestamps.

Poses are ``(N, 4, 4)`` float64 ``world_from_ego`` matrices. Numbers are written with Python's
shortest round-trip representation, so positions survive a write/read unchanged.
"""

from __future__ import annotations

import logging
import math
from decimal import Decimal, InvalidOperation
from pathlib import Path

import numpy as np

from radarslam.errors import DataError
from radarslam.geometry import (
    make_transform,
    quat_norm_problem,
    repair_rotations,
    rigid_problems,
    rotation_to_quat,
)
from radarslam.io.atomic import atomic_open
from radarslam.io.text import read_text
from radarslam.timestamps import check_timestamps_us

#: Tolerance of the rotation check (|R R^T - I|, |det R - 1|, bottom row), the same when writing
#: and reading: what the writers accept, the readers read back. Loose enough for poses printed
#: with few digits by other tools.
POSE_TOLERANCE = 1e-3

_INT64_MIN, _INT64_MAX = -(2**63), 2**63 - 1

log = logging.getLogger("radarslam.io")


def _check_poses(poses, what: str) -> np.ndarray:
    """(N, 4, 4) float64 rigid poses (float32 or lists converted), else :class:`DataError`."""
    try:
        arr = np.asarray(poses, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{what}: poses must be a numeric (N, 4, 4) array") from None
    if arr.ndim != 3 or arr.shape[1:] != (4, 4):
        raise DataError(f"{what}: poses must have shape (N, 4, 4), got {arr.shape}")
    bad = rigid_problems(arr, POSE_TOLERANCE)
    if bad is not None:
        raise DataError(f"{what}: pose {bad[0]} {bad[1]}")
    return arr


def _fmt(x: float) -> str:
    return repr(float(x))


def _us_to_seconds_text(t_us: int) -> str:
    t_us = int(t_us)
    sign = "-" if t_us < 0 else ""
    a = abs(t_us)
    return f"{sign}{a // 1_000_000}.{a % 1_000_000:06d}"


def _seconds_text_to_us(text: str) -> int:
    """Exact integer microseconds of a decimal seconds text; InvalidOperation when it is not a
    finite number, OverflowError when it does not fit int64."""
    # Decimal keeps nuScenes-sized timestamps (~1.5e15 us) exact where float64 seconds would not.
    value = Decimal(text)
    if not value.is_finite():
        raise InvalidOperation
    if value.adjusted() > 15:  # >= 1e16 s: never expand a huge exponent into an int
        raise OverflowError
    us = int((value * 1_000_000).to_integral_value())
    if not _INT64_MIN <= us <= _INT64_MAX:
        raise OverflowError
    return us


def write_tum(path: str | Path, timestamps_us, poses) -> None:
    """Write ``timestamp_s tx ty tz qx qy qz qw`` lines (evo's TUM format), atomically.

    What :func:`read_tum` would reject is a :class:`DataError` here, before anything is written:
    poses must be rigid (:data:`POSE_TOLERANCE`), timestamps strictly increasing integers."""
    arr = _check_poses(poses, str(path))
    ts = check_timestamps_us(timestamps_us, len(arr), str(path))
    lines = []
    for t, pose in zip(ts, arr, strict=True):
        w, x, y, z = rotation_to_quat(pose[:3, :3])
        tx, ty, tz = pose[:3, 3]
        fields = [_us_to_seconds_text(t)] + [_fmt(v) for v in (tx, ty, tz, x, y, z, w)]
        lines.append(" ".join(fields))
    with atomic_open(path, "w") as fh:
        fh.write("# timestamp_s tx ty tz qx qy qz qw\n")
        fh.write("".join(line + "\n" for line in lines))


def _data_lines(path: Path):
    text = read_text(path, "trajectory file")
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        # evo/TUM tools also accept comma separated values
        yield lineno, line.replace(",", " ").split()


def _floats(path: Path, lineno: int, tokens: list[str], start: int = 0) -> list[float]:
    try:
        values = [float(t) for t in tokens[start:]]
    except ValueError:
        raise DataError(f"{path}:{lineno}: non-numeric value in {' '.join(tokens)!r}") from None
    if not all(np.isfinite(values)):
        raise DataError(f"{path}:{lineno}: non-finite value in {' '.join(tokens)!r}")
    return values


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM file -> (timestamps_us (N,) int64, poses (N, 4, 4) float64).

    Timestamps must be strictly increasing (:class:`DataError` naming the line otherwise)."""
    path = Path(path)
    stamps: list[int] = []
    poses: list[np.ndarray] = []
    prev_lineno = 0
    for lineno, tokens in _data_lines(path):
        if len(tokens) != 8:
            raise DataError(
                f"{path}:{lineno}: expected 8 values (timestamp_s tx ty tz qx qy qz qw), "
                f"got {len(tokens)}"
            )
        try:
            stamps.append(_seconds_text_to_us(tokens[0]))
        except OverflowError:
            raise DataError(
                f"{path}:{lineno}: timestamp {tokens[0]!r} s is out of range (int64 microseconds "
                "hold |t| < 9.2e12 s)"
            ) from None
        except (ArithmeticError, ValueError):  # InvalidOperation, decimal Overflow, ...
            raise DataError(f"{path}:{lineno}: bad timestamp {tokens[0]!r}") from None
        if len(stamps) > 1 and stamps[-1] <= stamps[-2]:
            what = "repeats" if stamps[-1] == stamps[-2] else "is earlier than"
            raise DataError(
                f"{path}:{lineno}: timestamp {tokens[0]} {what} the previous one (line "
                f"{prev_lineno}); timestamps must be strictly increasing"
            )
        prev_lineno = lineno
        tx, ty, tz, qx, qy, qz, qw = _floats(path, lineno, tokens, 1)
        why = quat_norm_problem(math.hypot(qx, qy, qz, qw))
        if why is not None:
            what = "zero-norm quaternion" if why == "is zero" else f"quaternion {why}"
            raise DataError(f"{path}:{lineno}: {what}")
        poses.append(make_transform((tx, ty, tz), (qw, qx, qy, qz)))
    if not poses:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 4, 4))
    return np.asarray(stamps, dtype=np.int64), np.stack(poses)


def write_kitti(path: str | Path, poses) -> None:
    """Write each pose's 3x4 block as 12 numbers per line (KITTI odometry format), atomically.

    Poses must be rigid with bottom row (0, 0, 0, 1), as :func:`read_kitti` checks them."""
    arr = _check_poses(poses, str(path))
    with atomic_open(path, "w") as fh:
        for pose in arr:
            fh.write(" ".join(_fmt(v) for v in pose[:3, :4].reshape(-1)) + "\n")


def read_kitti(path: str | Path) -> np.ndarray:
    """Read a KITTI pose file -> (N, 4, 4) float64.

    Rotation blocks off by more than :data:`POSE_TOLERANCE` but at most
    :data:`~radarslam.geometry.REPAIR_TOLERANCE` (files printed with 6 decimals) are
    re-orthonormalised, with one warning for the file; beyond that a :class:`DataError` names
    the line."""
    path = Path(path)
    poses = []
    linenos = []
    for lineno, tokens in _data_lines(path):
        if len(tokens) != 12:
            raise DataError(f"{path}:{lineno}: expected 12 values (3x4 pose), got {len(tokens)}")
        pose = np.eye(4)
        pose[:3, :4] = np.asarray(_floats(path, lineno, tokens)).reshape(3, 4)
        poses.append(pose)
        linenos.append(lineno)
    if not poses:
        return np.zeros((0, 4, 4))
    try:
        fixed = repair_rotations(np.stack(poses), POSE_TOLERANCE)
    except ValueError as exc:
        i, why = exc.args
        raise DataError(
            f"{path}:{linenos[i]}: rotation block is not a rotation matrix: pose {why}"
        ) from None
    if fixed.count:
        log.warning(
            "%s: %d of %d rotation block(s) off by up to %.3g (max |R R^T - I|), as printed with "
            "few digits; re-orthonormalised",
            path,
            fixed.count,
            len(poses),
            fixed.worst,
        )
    return fixed.poses
