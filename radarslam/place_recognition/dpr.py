"""Dynamic Points Removal (AutoPlace Algorithm 1) built on the shared Doppler estimator.

Per radar sweep (in its own sensor frame, before accumulation):

1. Doppler ``v_r = u . (vx, vy)`` from the RAW velocity fields, ``u`` the line of sight.
2. Static ego: if more than ``static_fraction`` (p^tau = 0.5) of the points have
   ``|v_r| < static_speed_mps`` (v_r^tau = 1 m/s) the vehicle stands still; the slow points
   are kept.
3. Otherwise RANSAC fits the sensor velocity v_s to ``v_r = -u . v_s``; inliers are the points with
   ``|residual| < relative_threshold * |v_s|`` (tau = 0.15); they are static and kept, the
   outliers (moving targets, ghosts) are removed.

Both steps are :func:`radarslam.odometry.doppler.fit_sensor_velocity` (the odometry's estimator);
this module only decides which sweeps it runs on and what a failed fit means.

Departures from the AutoPlace reference code, on purpose:
- all five radars are filtered by default (the reference filters FRONT, BACK_LEFT, BACK_RIGHT only:
  ``DPRConfig.reference_three_radars()`` reproduces that);
- ``v_r`` is the signed projection on the line of sight in each sweep's own sensor frame (the
  reference folds angles with ``arctan`` and mixes the back radars' velocities with front-radar
  azimuths);
- the estimator draws 2-point minimal sets and refits the consensus by least squares (the reference
  fits 5 points with ``least_squares`` and does not refit);
- a sweep with 0 or 1 usable points, or on which no consistent velocity exists, is dropped
  (``drop_sweep_on_failure``) instead of crashing;
- the static-ego rule, which looks at one radar, is cross-checked (``verify_static_ego``): a side
  radar of a moving car sees many static points near broadside at |v_r| < 1 m/s and trips the
  rule, which would then keep only those. When plain RANSAC finds a speed >= v_r^tau explaining at
  least as many points as the rule kept, the sensor moves and the RANSAC inliers are kept.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from radarslam.odometry.doppler import fit_sensor_velocity
from radarslam.place_recognition.config import DPRConfig
from radarslam.types import RadarSweep


@dataclass
class DPRStats:
    """Counters over every sweep the filter saw (for the prepared cache's report)."""

    sweeps: int = 0
    sweeps_static_ego: int = 0
    sweeps_failed: int = 0
    points_in: int = 0
    points_kept: int = 0
    per_channel_removed: dict[str, int] = field(default_factory=dict)

    @property
    def removed_fraction(self) -> float:
        return 1.0 - self.points_kept / self.points_in if self.points_in else 0.0

    def merge(self, other: DPRStats) -> None:
        self.sweeps += other.sweeps
        self.sweeps_static_ego += other.sweeps_static_ego
        self.sweeps_failed += other.sweeps_failed
        self.points_in += other.points_in
        self.points_kept += other.points_kept
        for ch, k in other.per_channel_removed.items():
            self.per_channel_removed[ch] = self.per_channel_removed.get(ch, 0) + k

    def as_dict(self) -> dict:
        return {
            "sweeps": self.sweeps,
            "sweeps_static_ego": self.sweeps_static_ego,
            "sweeps_failed": self.sweeps_failed,
            "points_in": self.points_in,
            "points_kept": self.points_kept,
            "removed_fraction": round(self.removed_fraction, 6),
            "per_channel_removed": dict(sorted(self.per_channel_removed.items())),
        }


def dpr_mask(
    directions: np.ndarray, radial_velocity_mps: np.ndarray, cfg: DPRConfig
) -> tuple[np.ndarray, bool, bool]:
    """(keep mask, ego_static, fit_valid) for one sweep's lines of sight and raw Doppler."""
    n = len(radial_velocity_mps)
    if n == 0:
        return np.zeros(0, bool), False, True
    common: dict[str, Any] = dict(
        inlier_threshold_mps=cfg.inlier_threshold_mps,
        relative_threshold=cfg.relative_threshold,
        static_speed_mps=cfg.static_speed_mps,
        iterations=cfg.iterations,
        rng=cfg.seed,
    )
    fit = fit_sensor_velocity(
        directions, radial_velocity_mps, static_fraction=cfg.static_fraction, **common
    )
    if cfg.verify_static_ego and fit.valid and fit.ego_static:
        # a fraction above 1 can never be exceeded: this fit is plain RANSAC
        moving = fit_sensor_velocity(directions, radial_velocity_mps, static_fraction=1.0,
                                     **common)  # fmt: skip
        if (
            moving.valid
            and moving.speed_mps >= cfg.static_speed_mps
            and moving.num_inliers >= fit.num_inliers
        ):
            fit = moving  # the slow points were broadside targets of a moving sensor
    if not fit.valid:
        keep = np.zeros(n, bool) if cfg.drop_sweep_on_failure else np.ones(n, bool)
        return keep, False, False
    return fit.static_mask.copy(), bool(fit.ego_static), True


class DynamicPointsRemoval:
    """Callable ``sweep -> keep mask`` for the reader's ``point_mask`` hook; keeps statistics."""

    def __init__(self, cfg: DPRConfig | None = None):
        self.cfg = cfg or DPRConfig()
        self._channels = frozenset(self.cfg.channels)
        self.stats = DPRStats()

    def __call__(self, sweep: RadarSweep) -> np.ndarray:
        n = len(sweep)
        if not self.cfg.enabled or sweep.channel not in self._channels:
            return np.ones(n, bool)
        keep, static, valid = dpr_mask(sweep.unit_directions, sweep.radial_velocity, self.cfg)
        s = self.stats
        s.sweeps += 1
        s.sweeps_static_ego += int(static)
        s.sweeps_failed += int(not valid)
        s.points_in += n
        s.points_kept += int(keep.sum())
        s.per_channel_removed[sweep.channel] = s.per_channel_removed.get(sweep.channel, 0) + int(
            n - keep.sum()
        )
        return keep


def make_point_mask(cfg: DPRConfig | None) -> Callable[[RadarSweep], np.ndarray] | None:
    """The reader hook for a DPR config (None when DPR is disabled)."""
    if cfg is None or not cfg.enabled:
        return None
    return DynamicPointsRemoval(cfg)
