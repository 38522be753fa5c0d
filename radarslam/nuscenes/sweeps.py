"""What a sweep read keeps, what it counts as skipped, and how sweeps are stacked into one frame.

Points with a NaN/inf field or farther than :data:`MAX_POINT_COORDINATE_M` from their radar are
dropped and counted in :class:`SkipCounts`; :func:`stack_in_reference` puts many sweeps' points in
one reference frame, velocities rotated with the positions.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from radarslam.types import ACCUMULATED_DTYPE

_FLOAT_FIELDS = ("x", "y", "z", "rcs", "vx", "vy", "vx_comp", "vy_comp")
#: Largest |x|, |y| or |z| of a point in its sensor frame that is kept: four times the ARS408's
#: ~250 m far range.
MAX_POINT_COORDINATE_M = 1000.0


@dataclass
class SkipCounts:
    """What the reader skipped instead of failing (totals, and per scene name), each sweep counted
    once however often it is read."""

    nan_points: int = 0  # points dropped because a float field was NaN/inf
    empty_sweeps: int = 0  # sweeps with no point left (yielded with 0 points)
    far_points: int = 0  # finite points beyond MAX_POINT_COORDINATE_M, dropped
    per_scene: dict[str, dict[str, int]] = field(default_factory=dict)

    def add(self, scene: str, nan_points: int, empty: bool, far_points: int = 0) -> None:
        if not nan_points and not empty and not far_points:
            return
        self.nan_points += nan_points
        self.empty_sweeps += int(empty)
        self.far_points += far_points
        d = self.per_scene.setdefault(scene, dict.fromkeys(_SKIP_KEYS, 0))
        d["nan_points"] += nan_points
        d["empty_sweeps"] += int(empty)
        d["far_points"] += far_points


_SKIP_KEYS = ("nan_points", "empty_sweeps", "far_points")


def stack_in_reference(
    parts: Sequence[tuple[np.ndarray, np.ndarray, int, int, float]],
) -> np.ndarray:
    """The radar points (:data:`RADAR_DTYPE`) of every ``(points, ref_from_sensor,
    channel_index, sweep_index, time_lag_s)`` as :data:`ACCUMULATED_DTYPE` in the reference frame,
    concatenated: positions transformed, velocity vectors (vx, vy, 0) rotated with them in 3-D
    (the devkit leaves velocities in each sweep's sensor frame). One vectorised pass over all the
    sweeps of a cloud (35 per key frame) instead of a dozen numpy calls per sweep."""
    parts = [p for p in parts if len(p[0])]
    if not parts:
        return np.zeros(0, dtype=ACCUMULATED_DTYPE)
    counts = np.array([len(p[0]) for p in parts])
    pts = np.concatenate([p[0] for p in parts]) if len(parts) > 1 else parts[0][0]
    transforms = np.stack([np.asarray(p[1], dtype=np.float64) for p in parts])
    rot = np.repeat(transforms[:, :3, :3], counts, axis=0)  # (N, 3, 3), one per point
    out = np.zeros(len(pts), dtype=ACCUMULATED_DTYPE)
    xyz = np.column_stack([pts["x"], pts["y"], pts["z"]]).astype(np.float64)
    xyz = np.einsum("nij,nj->ni", rot, xyz) + np.repeat(transforms[:, :3, 3], counts, axis=0)
    out["x"], out["y"], out["z"] = xyz[:, 0], xyz[:, 1], xyz[:, 2]
    for a, b in (("vx", "vy"), ("vx_comp", "vy_comp")):
        v = np.column_stack([pts[a], pts[b]]).astype(np.float64)  # (vx, vy, 0)
        v = np.einsum("nij,nj->ni", rot[:, :2, :2], v)
        out[a], out[b] = v[:, 0], v[:, 1]
    out["rcs"] = pts["rcs"]
    out["dyn_prop"] = pts["dyn_prop"]
    out["channel"] = np.repeat([p[2] for p in parts], counts)
    out["sweep"] = np.repeat([p[3] for p in parts], counts)
    out["time_lag_s"] = np.repeat([p[4] for p in parts], counts)
    return out
