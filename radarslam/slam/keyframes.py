"""Key-frame clouds from the sweeps the odometry has already seen, placed with *estimated* poses.

The nuScenes devkit (and AutoPlace's preprocessing) accumulate the 7 past sweeps of each radar with
the ground-truth ``ego_pose``. A SLAM system must not look at ground truth, so here every sweep is
placed with the odometry pose of the frame it arrived in, de-skewed to its own timestamp with that
frame's Doppler twist (the radars fire up to ~77 ms apart). Everything else follows
:meth:`radarslam.nuscenes.reader.NuScenesRadar.accumulate`: the devkit's default point filters,
points closer than ``min_distance_m`` to their own sensor removed, velocities rotated with the
points, the cloud expressed in the reference radar's frame at the key frame.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from radarslam.geometry import invert
from radarslam.nuscenes.filters import RadarPointFilter
from radarslam.nuscenes.reader import stack_in_reference
from radarslam.odometry.lie import exp_se2
from radarslam.types import RADAR_CHANNELS, AccumulatedCloud, RadarSweep


@dataclass
class _BufferedSweep:
    sweep: RadarSweep
    world_from_ego: np.ndarray  # estimated pose of the ego at the sweep's own timestamp
    static: np.ndarray | None = None  # the odometry's static-point mask, when it gave one
    mask: np.ndarray | None = None  # filter & DPR mask, computed once, when first needed


class SweepBuffer:
    """The last ``nsweeps`` sweeps of every radar with their estimated poses."""

    def __init__(
        self,
        nsweeps: int = 7,
        channels: tuple[str, ...] | list[str] = RADAR_CHANNELS,
        ref_channel: str = "RADAR_FRONT",
        min_distance_m: float = 1.0,
        point_filter: RadarPointFilter | None = None,
        point_mask: Callable[[RadarSweep], np.ndarray] | None = None,
    ):
        self.nsweeps = nsweeps
        self.channels = tuple(channels)
        self.ref_channel = ref_channel
        self.min_distance_m = min_distance_m
        self.point_filter = point_filter or RadarPointFilter.devkit_default()
        self.point_mask = point_mask
        self._sweeps: dict[str, deque[_BufferedSweep]] = {
            ch: deque(maxlen=nsweeps) for ch in self.channels
        }
        self._calibration: dict[str, np.ndarray] = {}

    def clear(self) -> None:
        for q in self._sweeps.values():
            q.clear()

    def add_frame(
        self,
        frame,
        world_from_ego: np.ndarray,
        twist: np.ndarray,
        static_masks: dict[str, np.ndarray] | None = None,
    ) -> None:
        """Buffer a frame's sweeps; ``twist`` (vx, vy, yaw_rate) de-skews each to its own time.

        ``static_masks`` (channel -> bool per point, e.g. the odometry's joint Doppler inliers)
        replace ``point_mask`` for those sweeps: the frame's dynamic points are then removed by
        the fit the odometry already made instead of a second RANSAC per sweep.
        """
        for ch, sweep in frame.sweeps.items():
            if ch not in self._sweeps:
                continue
            self._calibration[ch] = sweep.ego_from_sensor
            dt_s = (sweep.timestamp_us - frame.timestamp_us) * 1e-6
            pose = world_from_ego @ exp_se2(np.asarray(twist, dtype=np.float64) * dt_s)
            static = None
            if static_masks is not None and ch in static_masks:
                static = np.asarray(static_masks[ch], dtype=bool)
                if static.shape != (len(sweep),):
                    raise ValueError(
                        f"static mask of {ch} has shape {static.shape}, "
                        f"the sweep has {len(sweep)} points"
                    )
            self._sweeps[ch].append(_BufferedSweep(sweep, pose, static))

    def _mask(self, item: _BufferedSweep) -> np.ndarray:
        if item.mask is None:
            pts = item.sweep.points
            keep = self.point_filter.mask(pts)
            r = np.hypot(pts["x"], pts["y"])
            keep &= np.isfinite(r) & (r >= self.min_distance_m)
            if item.static is not None:
                keep &= item.static
            elif self.point_mask is not None and keep.any():
                keep &= np.asarray(self.point_mask(item.sweep), dtype=bool)
            item.mask = keep
        return item.mask

    def accumulate(
        self, timestamp_us: int, world_from_ego: np.ndarray, sample_token: str = ""
    ) -> AccumulatedCloud | None:
        """The buffered sweeps in the reference radar's frame at ``timestamp_us`` (None before
        the reference radar's calibration is known)."""
        ego_from_ref = self._calibration.get(self.ref_channel)
        if ego_from_ref is None:
            return None
        ref_from_world = invert(world_from_ego @ ego_from_ref)
        parts, counts = [], {}
        for ch in self.channels:
            newest_first = [b for b in reversed(self._sweeps[ch])]
            for k, item in enumerate(newest_first):
                keep = self._mask(item)
                counts[(ch, k)] = int(np.count_nonzero(keep))
                if not counts[(ch, k)]:
                    continue
                s = item.sweep
                parts.append(
                    (
                        s.points[keep],
                        ref_from_world @ item.world_from_ego @ s.ego_from_sensor,
                        RADAR_CHANNELS.index(ch),
                        k,
                        (timestamp_us - s.timestamp_us) * 1e-6,
                    )
                )
        points = stack_in_reference(parts)
        return AccumulatedCloud(
            points=points,
            world_from_ref=world_from_ego @ ego_from_ref,
            ref_channel=self.ref_channel,
            timestamp_us=int(timestamp_us),
            sample_token=sample_token,
            num_points_per_sweep=counts,
        )

    def ego_from_ref(self) -> np.ndarray | None:
        return self._calibration.get(self.ref_channel)
