"""Baselines the odometry is compared against (bench/odometry.py, ``radarslam odometry --method``).

* ``doppler``: Doppler dead reckoning: :class:`~.pipeline.RadarOdometry` with
  ``fusion.mode="doppler"`` (no registration).
* ``kiss-icp``: kiss-icp's own ``KissICP`` pipeline (constant-velocity prediction, adaptive
  threshold, its voxel-hash map), fed exactly the points our odometry registers: the Doppler
  inliers of all radars in the ego frame, de-skewed with the Doppler twist, z = 0. kiss-icp's own
  de-skewing is off (it needs per-point timestamps of a spinning lidar). Its config for sparse
  radar: voxel 1 m, max range 100 m, min range 1 m, 20 points per voxel, one thread.

Both guard against kiss-icp's abort (Sophus, on a rotation drifted off SO(3)): frames with too
few points are not given to it (the pose is extrapolated with its own constant velocity instead),
and its pose and delta are re-orthonormalised after every frame.
"""

from __future__ import annotations

import time

import numpy as np

from radarslam.odometry.config import OdometryConfig
from radarslam.odometry.doppler import DopplerEstimator
from radarslam.odometry.lie import planar
from radarslam.odometry.pipeline import FrameTiming, OdometryResult, RadarOdometry
from radarslam.types import RadarFrame

METHODS = ("ours", "doppler", "kiss-icp")


class PlainKissIcpOdometry:
    """kiss-icp's ``KissICP`` pipeline on our dynamic-free, de-skewed ego-frame points."""

    def __init__(self, config: OdometryConfig | None = None):
        self.config = config or OdometryConfig()
        self.doppler = DopplerEstimator(self.config.doppler)
        # Reuse the exact point preparation of our odometry (same inputs, stated in the bench).
        self._points = RadarOdometry(self.config)
        self.reset()

    def reset(self) -> None:
        self._kiss = None
        self._origin = np.eye(4)
        self._last: np.ndarray | None = None

    def _make_kiss(self):
        from kiss_icp.config import load_config
        from kiss_icp.kiss_icp import KissICP

        r = self.config.registration
        cfg = load_config(None)
        cfg.data.max_range = self.config.points.max_range_m
        cfg.data.min_range = self.config.points.min_range_m
        cfg.data.deskew = False
        cfg.mapping.voxel_size = r.voxel_size_m
        cfg.mapping.max_points_per_voxel = r.max_points_per_voxel
        cfg.registration.max_num_threads = 1
        return KissICP(config=cfg)

    def process(self, frame: RadarFrame) -> OdometryResult:
        t0 = time.perf_counter()
        # DataError on a non-rigid / non-finite pose or calibration: kiss-icp would abort on it.
        ground_truth = self._points.check_frame(frame)
        fit = self.doppler.fit_frame(frame)
        t1 = time.perf_counter()
        points = self._points.ego_points(frame, fit, fit.twist)
        t2 = time.perf_counter()
        first = self._kiss is None
        if first:
            self._kiss = self._make_kiss()
            if self.config.initial_pose == "ground_truth":
                self._origin = planar(ground_truth)
        kiss = self._kiss
        # Re-orthonormalise before kiss-icp composes last_pose @ last_delta in numpy: Sophus aborts
        # the whole process on a rotation that is not orthogonal.
        kiss.last_pose = planar(kiss.last_pose)
        kiss.last_delta = planar(kiss.last_delta)
        min_pts = self.config.registration.min_source_points
        if len(points) >= min_pts or (first and len(points)):
            kiss.register_frame(points, np.zeros(len(points)))
            status = "kiss-icp"
        else:
            # What kiss-icp would predict, without feeding it an empty frame.
            kiss.last_pose = kiss.last_pose @ kiss.last_delta
            status = "skipped"
        kiss.last_pose = planar(kiss.last_pose)
        kiss.last_delta = planar(kiss.last_delta)
        t3 = time.perf_counter()
        pose = self._origin @ kiss.last_pose
        relative = np.eye(4) if self._last is None else np.linalg.inv(self._last) @ pose
        self._last = pose
        return OdometryResult(
            timestamp_us=int(frame.timestamp_us),
            world_from_ego=pose,
            pose_covariance=np.full((3, 3), np.nan),
            relative_motion=planar(relative),
            relative_covariance=np.full((3, 3), np.nan),  # kiss-icp reports none
            doppler=fit,
            registration=None,
            icp_accepted=status == "kiss-icp",
            status="first" if first else status,
            num_points=len(points),
            timing=FrameTiming((t1 - t0) * 1e3, (t2 - t1) * 1e3, (t3 - t2) * 1e3, (t3 - t0) * 1e3),
            ground_truth=ground_truth,
            is_key_frame=bool(frame.is_key_frame),
            sample_token=frame.sample_token,
            scene_name=frame.scene_name,
        )


def make_odometry(method: str, config: OdometryConfig | None = None):
    """An odometry object with ``process(frame)`` and ``reset()`` for one of :data:`METHODS`."""
    from radarslam.errors import ConfigError

    config = config or OdometryConfig()
    if method == "ours":
        return RadarOdometry(config)
    if method == "doppler":
        cfg = config.model_copy(deep=True)
        cfg.fusion.mode = "doppler"
        return RadarOdometry(cfg)
    if method == "kiss-icp":
        return PlainKissIcpOdometry(config)
    raise ConfigError(f"unknown odometry method {method!r}; choose one of {', '.join(METHODS)}")
