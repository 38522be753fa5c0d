"""Typed records shared by every stage.

Conventions (also in docs/DEVELOPING.md):
- Timestamps are integer microseconds (``timestamp_us``), as in nuScenes; durations derived from
  them are float seconds named ``*_s``.
- Poses are 4x4 float64 matrices named ``a_from_b``; frames are ``world`` (nuScenes global),
  ``ego`` (the vehicle's rear axle, nuScenes ``ego_pose``) and ``sensor`` (one radar).
- Radar points are structured numpy arrays of :data:`RADAR_DTYPE` (the 18 nuScenes fields) in the
  sensor frame, x forward along the boresight, z = 0.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

RADAR_CHANNELS: tuple[str, ...] = (
    "RADAR_FRONT",
    "RADAR_FRONT_LEFT",
    "RADAR_FRONT_RIGHT",
    "RADAR_BACK_LEFT",
    "RADAR_BACK_RIGHT",
)


def check_radar_channel(name: str) -> str:
    """``name`` when it is one of :data:`RADAR_CHANNELS`, else ValueError (a config validator)."""
    if name not in RADAR_CHANNELS:
        raise ValueError(f"unknown radar channel {name!r} (one of {', '.join(RADAR_CHANNELS)})")
    return name


RADAR_FIELDS: tuple[str, ...] = (
    "x", "y", "z", "dyn_prop", "id", "rcs", "vx", "vy", "vx_comp", "vy_comp", "is_quality_valid",
    "ambig_state", "x_rms", "y_rms", "invalid_state", "pdh0", "vx_rms", "vy_rms",
)  # fmt: skip

#: One packed little-endian 43-byte record of a nuScenes radar ``.pcd`` file, in FIELDS order.
RADAR_DTYPE = np.dtype(
    [
        ("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("dyn_prop", "i1"), ("id", "<i2"),
        ("rcs", "<f4"), ("vx", "<f4"), ("vy", "<f4"), ("vx_comp", "<f4"), ("vy_comp", "<f4"),
        ("is_quality_valid", "i1"), ("ambig_state", "i1"), ("x_rms", "i1"), ("y_rms", "i1"),
        ("invalid_state", "i1"), ("pdh0", "i1"), ("vx_rms", "i1"), ("vy_rms", "i1"),
    ]
)  # fmt: skip
assert RADAR_DTYPE.itemsize == 43

#: Points of an accumulated multi-sweep, multi-radar cloud expressed in one reference frame.
#: Velocities are rotated into the reference frame with the points (the devkit leaves them in
#: each sweep's own sensor frame).
ACCUMULATED_DTYPE = np.dtype(
    [
        ("x", "<f8"), ("y", "<f8"), ("z", "<f8"), ("rcs", "<f4"),
        ("vx", "<f4"), ("vy", "<f4"), ("vx_comp", "<f4"), ("vy_comp", "<f4"),
        ("dyn_prop", "i1"), ("channel", "i1"), ("sweep", "i1"), ("time_lag_s", "<f4"),
    ]
)  # fmt: skip


@dataclass(frozen=True, eq=False)
class RadarSweep:
    """One radar's sweep: points in its sensor frame plus calibration and ground-truth pose."""

    channel: str
    timestamp_us: int
    points: np.ndarray  # structured, RADAR_DTYPE, sensor frame
    ego_from_sensor: np.ndarray  # 4x4 float64 (calibrated_sensor)
    world_from_ego: np.ndarray  # 4x4 float64 (ego_pose of this sample_data: ground truth)
    is_key_frame: bool = False
    token: str = ""  # sample_data token
    sample_token: str = ""
    filename: str = ""  # relative to the dataroot

    def __len__(self) -> int:
        return len(self.points)

    @property
    def xy(self) -> np.ndarray:
        """(N, 2) float64 positions in the sensor frame."""
        return np.column_stack([self.points["x"], self.points["y"]]).astype(np.float64)

    @property
    def velocity(self) -> np.ndarray:
        """(N, 2) raw relative velocity (vx, vy) in the sensor frame (not purely radial)."""
        return np.column_stack([self.points["vx"], self.points["vy"]]).astype(np.float64)

    @property
    def velocity_comp(self) -> np.ndarray:
        """(N, 2) ego-motion-compensated velocity (vx_comp, vy_comp): purely radial."""
        return np.column_stack([self.points["vx_comp"], self.points["vy_comp"]]).astype(np.float64)

    @property
    def unit_directions(self) -> np.ndarray:
        """(N, 2) line-of-sight unit vectors u = (x, y) / |(x, y)|."""
        xy = self.xy
        r = np.linalg.norm(xy, axis=1, keepdims=True)
        return xy / np.maximum(r, 1e-9)

    @property
    def radial_velocity(self) -> np.ndarray:
        """(N,) Doppler measurement v_r = u . (vx, vy) from the raw velocity."""
        return np.einsum("ij,ij->i", self.unit_directions, self.velocity)

    @property
    def world_from_sensor(self) -> np.ndarray:
        return self.world_from_ego @ self.ego_from_sensor

    def with_points(self, points: np.ndarray) -> RadarSweep:
        """A copy holding another point array (e.g. a masked subset)."""
        return RadarSweep(
            channel=self.channel,
            timestamp_us=self.timestamp_us,
            points=points,
            ego_from_sensor=self.ego_from_sensor,
            world_from_ego=self.world_from_ego,
            is_key_frame=self.is_key_frame,
            token=self.token,
            sample_token=self.sample_token,
            filename=self.filename,
        )


@dataclass(frozen=True, eq=False)
class RadarFrame:
    """The five radars' sweeps nearest in time (a "sweep set"), the unit odometry consumes.

    A channel that has no sweep near ``timestamp_us`` is simply absent from ``sweeps``.
    """

    timestamp_us: int  # reference time of the set (the reference channel's sweep)
    sweeps: dict[str, RadarSweep]
    world_from_ego: np.ndarray  # ground truth at timestamp_us
    scene_name: str = ""
    is_key_frame: bool = False
    sample_token: str = ""  # set on key frames

    @property
    def num_points(self) -> int:
        return sum(len(s) for s in self.sweeps.values())


@dataclass(frozen=True, eq=False)
class AccumulatedCloud:
    """N sweeps x several radars accumulated into one reference frame at a key frame."""

    points: np.ndarray  # structured, ACCUMULATED_DTYPE, in the reference frame
    world_from_ref: np.ndarray  # 4x4: where the reference frame is (sensor or ego at the key frame)
    ref_channel: str | None  # None when the reference frame is the ego frame
    timestamp_us: int
    sample_token: str = ""
    num_points_per_sweep: dict[tuple[str, int], int] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.points)

    @property
    def xy(self) -> np.ndarray:
        return np.column_stack([self.points["x"], self.points["y"]])


@dataclass(frozen=True)
class SceneInfo:
    """One nuScenes scene with what multi-session selection needs."""

    name: str
    token: str
    log_token: str
    location: str
    date_captured: str  # YYYY-MM-DD as in log.json
    vehicle: str
    nbr_samples: int
    first_sample_token: str
    last_sample_token: str
    description: str = ""
