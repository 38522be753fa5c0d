"""Radar odometry: Doppler ego-motion + kiss-icp scan-to-map registration, fused per frame.

Per frame (the five radars' sweeps nearest in time, :class:`~radarslam.types.RadarFrame`):

1. **Doppler** (:mod:`.doppler`): one joint RANSAC + least-squares fit of the rear axle's twist
   ``(vx, vy, yaw_rate)`` from all radars (Kellner et al. 2014), with its covariance and the static
   (inlier) points of every radar.
2. **Points**: the static points of every radar are moved to the ego frame and *de-skewed* to the
   frame's reference time with the Doppler twist (the radars fire up to ~77 ms apart: at 15 m/s
   that is a metre), then lifted to z = 0.
3. **Prediction**: the motion since the previous frame is the Doppler twist (trapezoid of the two
   frames' twists) integrated on SE(2); its covariance is the twists' covariances propagated
   through the SE(2) exponential plus a random-walk process noise.
4. **Registration**: kiss-icp's own registration aligns the points to kiss-icp's voxel-hash local
   map, seeded with the predicted pose turned at the previous frame's fused yaw rate (the
   Doppler's translation, kiss-icp's constant-velocity rotation), then a point-to-local-mean
   Gauss-Newton refinement finishes the alignment. Its covariance is the
   point-to-line Hessian at the solution (:mod:`.registration`).
5. **Fusion** (choice documented in docs/odometry.md): an error-state Kalman filter on SE(2).
   The Doppler motion is the filter's *input* (prediction), the registration is a *measurement of
   the pose in the map*. Treating scan-to-map ICP as a map-relative measurement rather than as a
   frame-to-frame delta is what keeps its errors from accumulating, while the Doppler prediction
   fills in what the geometry cannot see (a corridor, an empty frame). A Mahalanobis gate on the
   innovation rejects registrations that disagree with the prediction (ICP falls into a wrong
   minimum, moving objects dominate), in which case the frame keeps the Doppler pose; after
   ``max_consecutive_rejections`` rejections in a row the registration is accepted again
   (re-localisation in the map). Frames with too few points skip registration, and so do frames
   where the vehicle is stopped (static-ego rule and a twist indistinguishable from 0, at this
   frame and the previous one): the pose is held exactly (zero-velocity update).
6. The frame's points are inserted in the map at the fused pose.

Relative motion and covariance for the back end. For consecutive frames, and from key frame to key
frame (the unit the pose graph uses), the relative motion is the difference of the fused poses;
its covariance is the information-weighted fusion of two estimates of that motion: Doppler dead
reckoning over the interval (covariance propagated frame by frame) and the difference of the two
endpoints' map-relative registrations (covariance ``R_i + R_j``, conservative because both are
registered against the same map). When either endpoint was not registered it is the dead-reckoning
covariance alone.

Every pose is built from SE(2) exponentials (exactly orthonormal), and kiss-icp's output is
projected back onto SE(2), so the rotation can never drift off SO(3) (kiss-icp's Sophus aborts
the process when it does).
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field

import numpy as np

from radarslam.errors import ConfigError, DataError
from radarslam.geometry import invert, rigid_problem
from radarslam.odometry.calibration import (
    DopplerCalibration,
    Rig,
    find_rig,
    merge_extrinsics,
    rig_extrinsics,
    with_mounting,
)
from radarslam.odometry.config import OdometryConfig
from radarslam.odometry.doppler import DopplerEstimator, EgoMotionFit, TwistBounds, TwistRate
from radarslam.odometry.lie import adjoint_se2, exp_jacobian_twist, exp_se2, log_se2, planar
from radarslam.odometry.linalg3 import inv3, solve3
from radarslam.odometry.registration import RegistrationResult, ScanToMapRegistration
from radarslam.types import RADAR_CHANNELS, RadarFrame


@dataclass(frozen=True)
class FrameTiming:
    doppler_ms: float
    points_ms: float
    registration_ms: float
    total_ms: float


@dataclass(frozen=True)
class OdometryResult:
    """The odometry estimate at one frame."""

    timestamp_us: int
    world_from_ego: np.ndarray  # 4x4 estimate (SE(2), z = 0)
    pose_covariance: np.ndarray  # (3, 3) filter covariance, body tangent (x, y, yaw)
    relative_motion: np.ndarray  # 4x4 prev_ego_from_ego (identity at a segment's first frame)
    relative_covariance: np.ndarray  # (3, 3) of relative_motion, body tangent of the new pose
    doppler: EgoMotionFit
    registration: RegistrationResult | None  # None when registration was skipped
    icp_accepted: bool
    status: str  # "first" | "fused" | "icp" | "rejected" | "skipped" | "stopped" | "doppler"
    num_points: int  # points that entered registration (dynamic-free, in range)
    timing: FrameTiming
    ground_truth: np.ndarray  # the frame's world_from_ego from the dataset
    #: A key frame of the odometry: a dataset key frame (nuScenes sample) that the
    #: :class:`KeyFrameGate`, if any, let through.
    is_key_frame: bool = False
    sample_token: str = ""
    scene_name: str = ""
    #: Set on key frames (except a segment's first): motion since the previous key frame.
    key_frame_motion: np.ndarray | None = None
    key_frame_covariance: np.ndarray | None = None


@dataclass(frozen=True)
class KeyFrameGate:
    """Which dataset key frames become odometry key frames: one is passed over while the vehicle
    has moved less than ``min_travel_m`` and turned less than ``min_turn_deg`` since the previous
    key frame, unless ``max_interval_s`` (None: no limit) have passed (a car waiting at a light
    would otherwise add the same place every 0.5 s). ``min_travel_m = 0`` passes every one."""

    min_travel_m: float = 0.0
    min_turn_deg: float = 5.0
    max_interval_s: float | None = None

    def __post_init__(self) -> None:
        if not (self.min_travel_m >= 0 and math.isfinite(self.min_travel_m)):
            raise ConfigError(f"key-frame min_travel_m must be >= 0, got {self.min_travel_m!r}")
        if not (self.min_turn_deg > 0 and math.isfinite(self.min_turn_deg)):
            raise ConfigError(f"key-frame min_turn_deg must be > 0, got {self.min_turn_deg!r}")
        if self.max_interval_s is not None and not self.max_interval_s > 0:
            raise ConfigError(f"key-frame max_interval_s must be > 0, got {self.max_interval_s!r}")

    def keeps(self, motion: np.ndarray, interval_s: float) -> bool:
        """Whether a key frame at ``motion`` (4x4 prev_key_from_here) and ``interval_s`` after
        the last one counts."""
        if self.max_interval_s is not None and interval_s >= self.max_interval_s:
            return True
        travel = math.hypot(motion[0, 3], motion[1, 3])
        turn = abs(math.degrees(math.atan2(motion[1, 0], motion[0, 0])))
        return travel >= self.min_travel_m or turn >= self.min_turn_deg


@dataclass(frozen=True)
class _FrameTwist:
    """A frame's twist for the prediction: the Doppler fit's, or the last one held."""

    twist: np.ndarray  # (vx, vy, yaw_rate)
    cov: np.ndarray  # (3, 3)
    stopped: bool  # zero-velocity update: the static rule fired and the twist is 0
    gap_s: float  # since the previous frame (0 at a segment's first)


@dataclass(frozen=True)
class _Prediction:
    """The filter's prediction at a frame, before the registration."""

    pose: np.ndarray  # 4x4 world_from_ego
    cov: np.ndarray  # (3, 3) body tangent
    delta: np.ndarray  # 4x4 motion since the previous frame (identity at a segment's first)
    delta_cov: np.ndarray  # (3, 3) of delta
    calib_jacobian: np.ndarray | None  # pose error per calibration error (None at the first)


@dataclass(frozen=True)
class _Registered:
    """A frame's pose after its registration, fused or not."""

    pose: np.ndarray
    cov: np.ndarray
    result: RegistrationResult | None  # None when the registration did not run
    accepted: bool
    icp_cov: np.ndarray | None  # the accepted registration's covariance
    status: str  # as OdometryResult.status


@dataclass
class _Interval:
    """Dead-reckoning covariance accumulated since an anchor frame, and the anchor's ICP cov."""

    cov: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    #: The turn-rate error common to both sources (fusion.turn_sigma_per_radps), added after
    #: the interval's registrations are fused in.
    turn_cov: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))
    #: Motion error per calibration error over the interval: one calibration error biases every
    #: frame of it alike, so its share is added once at the end, not per frame.
    calib_jac: np.ndarray | None = None
    anchor_pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    anchor_icp_cov: np.ndarray | None = None
    anchor_us: int = 0

    def propagate(
        self,
        delta: np.ndarray,
        delta_cov: np.ndarray,
        calib_jac: np.ndarray,
        turn_cov: np.ndarray,
    ) -> None:
        ad = adjoint_se2(invert(delta))
        self.cov = ad @ self.cov @ ad.T + delta_cov
        self.turn_cov = ad @ self.turn_cov @ ad.T + turn_cov
        prev = np.zeros_like(calib_jac) if self.calib_jac is None else self.calib_jac
        self.calib_jac = ad @ prev + calib_jac

    def relative(
        self, pose: np.ndarray, icp_cov: np.ndarray | None, calib_cov: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        motion = invert(self.anchor_pose) @ pose
        cov = self.cov
        if self.calib_jac is not None:
            cov = cov + self.calib_jac @ calib_cov @ self.calib_jac.T
        if icp_cov is not None and self.anchor_icp_cov is not None:
            cov = _fuse_cov(cov, self.anchor_icp_cov + icp_cov)
        return motion, cov + self.turn_cov

    def reset(self, pose: np.ndarray, icp_cov: np.ndarray | None, timestamp_us: int) -> None:
        self.cov = np.zeros((3, 3))
        self.turn_cov = np.zeros((3, 3))
        self.calib_jac = None
        self.anchor_pose = pose
        self.anchor_icp_cov = icp_cov
        self.anchor_us = timestamp_us


def along_track_covariance(delta: np.ndarray, fraction: float) -> np.ndarray:
    """(3, 3) variance ``(fraction * |step|)^2`` along the translation of ``delta`` (a relative
    SE(2) motion, 4x4), in the body frame of the pose it ends at (the fusion's right
    perturbation); zero when it does not move."""
    step = np.asarray(delta, dtype=np.float64)[:2, 3]
    # The motion direction expressed at the end pose: R_delta^T step.
    u = step @ np.asarray(delta, dtype=np.float64)[:2, :2]
    out = np.zeros((3, 3))
    out[:2, :2] = fraction**2 * np.outer(u, u)
    return out


def _fuse_cov(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Covariance of the information-weighted fusion of two independent estimates."""
    info = inv3(a + np.eye(3) * 1e-12) + inv3(b + np.eye(3) * 1e-12)
    out = inv3(info)
    return 0.5 * (out + out.T)


#: chi-square, 3 dof, 99.9 %: a static-rule twist closer than this to 0 is taken as exactly 0
#: (at 99 % one stopped frame in a hundred would integrate its noise).
_ZERO_VELOCITY_CHI2 = 16.27
#: Widest yaw search (each side): beyond it a scan's few points match anywhere somewhat.
_YAW_SEARCH_MAX_RAD = np.deg2rad(20.0)


def _chi2(x: np.ndarray, cov: np.ndarray) -> float:
    try:
        return float(x @ solve3(cov, x))
    except np.linalg.LinAlgError:
        return float("inf")


def _sym(m: np.ndarray) -> np.ndarray:
    return 0.5 * (m + m.T)


#: Distinct checked calibrations remembered per odometry object (5 radars; a dataset has a few).
_MAX_CALIBRATIONS = 1024


def _is_int_us(t) -> bool:
    """Integer microseconds: an int (not bool), a numpy integer, or an integral float."""
    return type(t) is int or isinstance(t, np.integer) or (isinstance(t, float) and t.is_integer())


def _where(frame: RadarFrame) -> str:
    return f"frame at {frame.timestamp_us!r} us (scene {frame.scene_name or '?'})"


class RadarOdometry:
    """Streaming radar odometry: ``process(frame)`` once per frame, in time order.

    Key frames are the dataset's (nuScenes samples), thinned by ``key_frame_gate`` if given;
    the motion and covariance between two of them cover any passed over in between."""

    def __init__(
        self, config: OdometryConfig | None = None, key_frame_gate: KeyFrameGate | None = None
    ):
        self.config = config or OdometryConfig()
        self.key_frame_gate = key_frame_gate
        self.doppler = DopplerEstimator(self.config.doppler)
        self._q = np.diag(np.square(self.config.fusion.process_noise))
        self._growth = np.diag(self.config.fusion.invalid_doppler_growth)
        self._twist_floor = np.diag(np.square(self.config.fusion.twist_sigma_floor))
        self._turn_q = np.diag(np.square(self.config.fusion.turn_sigma_per_radps))
        cal = self.config.fusion.calibration
        #: Doppler calibration estimated by the filter, kept across segments (it belongs to the
        #: car): the yaw-rate bias (rad/m or rad/s), or with ``yaw_bias_model: mounting`` the
        #: five radars' mounting-yaw errors (rad, RADAR_CHANNELS order); then the speed-scale
        #: error.
        n_yaw = len(RADAR_CHANNELS) if cal.yaw_bias_model == "mounting" else 1
        #: Whether the Doppler residuals update the mounting yaws (``residual_cov_scale``): they
        #: complement the registration, so not without one (Doppler dead reckoning stays plain).
        self._residuals = (
            cal.yaw_bias_model == "mounting"
            and cal.residual_cov_scale is not None
            and self.config.fusion.mode == "kalman"
            and self.config.registration.enabled
        )
        self._calib = np.zeros(n_yaw + 1)
        self._calib_cov = np.diag(np.square([cal.yaw_bias_prior] * n_yaw + [cal.speed_scale_prior]))
        self._calib_q = np.diag(np.square([cal.yaw_bias_walk] * n_yaw + [cal.speed_scale_walk]))
        #: Mounting yaws (rad, RADAR_CHANNELS order) folded into the sweeps at resets.
        self._folded = np.zeros(len(RADAR_CHANNELS))
        self._mounting = self._mounting_transforms()
        #: The calibration above is the active rig's; the other rigs seen keep theirs here. A
        #: segment of another rig (nominal extrinsics differ) starts from that rig's calibration,
        #: or from the prior: a Singapore car's mounting errors applied to a Boston car's scenes
        #: moved those scenes' real ATE from 0.095 / 0.086 to 0.126 / 0.137 m.
        self._rig: Rig | None = None
        self._rigs: list[Rig] = []
        #: Bytes of the ego_from_sensor matrices already checked rigid: the calibration
        #: of a radar repeats in every sweep, so each is checked once, not 5 times a frame.
        self._good_calibrations: set[tuple[str, bytes]] = set()
        self.reset()

    def _mounting_transforms(self) -> dict[str, np.ndarray]:
        """Per channel, the sensor rotation applied to every sweep: the configured mounting
        yaws plus those folded in at resets."""
        given = self.config.mounting_yaw_deg
        out = {}
        for i, ch in enumerate(RADAR_CHANNELS):
            rad = math.radians(given.get(ch, 0.0)) + float(self._folded[i])
            if ch in given or rad != 0.0:
                out[ch] = exp_se2(np.array([0.0, 0.0, rad]))
        return out

    def _fold_calibration(self) -> None:
        """Apply the estimated mounting yaws to the sweeps from now on and zero the states."""
        cal = self.config.fusion.calibration
        n = len(RADAR_CHANNELS)
        if cal.yaw_bias_model != "mounting" or not cal.fold_at_reset or not self._calib[:n].any():
            return
        self._folded = self._folded + self._calib[:n]
        self._calib[:n] = 0.0
        self._mounting = self._mounting_transforms()

    def fold_calibration(self) -> None:
        """Between two scenes of one drive, where the odometry goes on without a reset: the
        estimated mounting yaws are applied to the sweeps from now on, as at a reset (with
        ``fusion.calibration.fold_at_reset``), the pose and the local map kept."""
        self._fold_calibration()

    def reset(self) -> None:
        """Forget everything (start a new segment); the calibration is kept (and folded into
        the sweeps with ``fusion.calibration.fold_at_reset``)."""
        self._fold_calibration()
        #: The segment's rig is chosen at its first frame with sweeps.
        self._rig_pending = True
        self._registration: ScanToMapRegistration | None = None
        self._pose: np.ndarray | None = None
        self._cov = np.zeros((3, 3))
        # covariance of the pose error with the calibration's
        self._cross = np.zeros((3, len(self._calib)))
        self._t_us: int | None = None
        self._twist = np.zeros(3)
        self._twist_cov = np.eye(3)
        #: Yaw rate of the previous frame's fused motion (rad/s): the registration's seed.
        self._fused_yaw_rate: float | None = None
        self._stopped = False
        self._last_icp_cov: np.ndarray | None = None
        #: Covariance of the motion since the last accepted registration (body frame).
        self._unregistered_cov = np.zeros((3, 3))
        self._rejections = 0
        self._kf = _Interval()
        self._kf_started = False
        #: The last valid Doppler fit: its twist (the centre of the next fit's bounds), the
        #: covariance the filter gave it (that of the twist held while fits are invalid), its time.
        self._last_fit: tuple[np.ndarray, np.ndarray, int] | None = None
        window = self.config.fusion.twist_rate_window_s
        self._rate = None if window is None else TwistRate(window)

    def _twist_bounds(self, timestamp_us: int) -> TwistBounds | None:
        rate = self.config.fusion.max_twist_rate
        if rate is None or self._last_fit is None:
            return None
        twist, _, t_us = self._last_fit
        dt_s = max((timestamp_us - t_us) * 1e-6, 1e-3)
        return TwistBounds(twist, np.asarray(rate, dtype=np.float64) * dt_s)

    @property
    def calibration(self) -> DopplerCalibration:
        """The Doppler calibration estimated so far for the rig of the latest segment (kept
        across that rig's segments)."""
        return self._calibration_of(self._calib, self._calib_cov, self._folded, self._rig)

    @property
    def calibrations(self) -> list[DopplerCalibration]:
        """The calibration of every rig seen, in the order first seen."""
        return [
            self.calibration
            if r is self._rig
            else self._calibration_of(r.calib, r.calib_cov, r.folded, r)
            for r in self._rigs
        ]

    def _calibration_of(
        self, calib: np.ndarray, calib_cov: np.ndarray, folded: np.ndarray, rig: Rig | None
    ) -> DopplerCalibration:
        sig = np.sqrt(np.diag(calib_cov))
        n = len(calib) - 1
        offset = folded if n == len(folded) else np.zeros(n)  # folded: "mounting" only
        return DopplerCalibration(
            self.config.fusion.calibration.yaw_bias_model,
            tuple(float(v) for v in calib[:-1] + offset),
            tuple(float(v) for v in sig[:-1]),
            float(calib[-1]),
            float(sig[-1]),
            self.config.doppler.speed_scale_error,
            rig="" if rig is None else rig.name,
            scenes=() if rig is None else tuple(rig.scenes),
        )

    def _store_rig(self) -> None:
        """Write the active calibration back to its rig's record."""
        if self._rig is not None:
            self._rig.calib = self._calib.copy()
            self._rig.calib_cov = self._calib_cov.copy()
            self._rig.folded = self._folded.copy()

    def _select_rig(self, frame: RadarFrame) -> None:
        """At a segment's first frame with sweeps: make the frame's rig the active one. A frame
        that shares no channel with the active rig, or disagrees with none it shares, stays
        with it."""
        extrinsics = rig_extrinsics(frame)
        self._rig_pending = not extrinsics
        if not extrinsics:
            return
        active = self._rig
        current = None if active is None else self._rigs.index(active)
        found = find_rig([r.extrinsics for r in self._rigs], extrinsics, current)
        if found is not None:
            merge_extrinsics(self._rigs[found].extrinsics, extrinsics)
            if found == current:
                return
        self._store_rig()
        if found is None:
            if active is None:  # the first rig takes the calibration the run started with
                calib, calib_cov, folded = self._calib, self._calib_cov, self._folded
            else:
                calib, calib_cov, folded = self._prior_calibration()
            rig = Rig(dict(extrinsics), calib.copy(), calib_cov, folded)
            self._rigs.append(rig)
        else:
            rig = self._rigs[found]
        self._rig = rig
        self._cross = np.zeros((3, len(rig.calib)))
        self._calib, self._calib_cov = rig.calib.copy(), rig.calib_cov.copy()
        self._folded = rig.folded.copy()
        self._mounting = self._mounting_transforms()

    def _prior_calibration(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Calibration states, covariance and folded mounting yaws of a rig not seen yet."""
        cal = self.config.fusion.calibration
        n_yaw = len(self._calib) - 1
        cov = np.diag(np.square([cal.yaw_bias_prior] * n_yaw + [cal.speed_scale_prior]))
        return np.zeros(len(self._calib)), cov, np.zeros(len(RADAR_CHANNELS))

    def _new_registration(self) -> ScanToMapRegistration | None:
        r = self.config.registration
        if not r.enabled or self.config.fusion.mode == "doppler":
            return None
        return ScanToMapRegistration(
            voxel_size_m=r.voxel_size_m,
            max_range_m=self.config.points.max_range_m,
            max_points_per_voxel=r.max_points_per_voxel,
            max_num_iterations=r.max_num_iterations,
            point_to_point=r.point_to_point,
            convergence_criterion=r.convergence_criterion,
            fixed_sigma_m=r.fixed_sigma_m,
            point_sigma_m=r.point_sigma_m,
            line_neighbors=r.line_neighbors,
            mirror_every=r.mirror_every,
            refine_iterations=r.refine_iterations,
            refine_max_extrapolation=r.refine_max_extrapolation,
        )

    # --- input checks -------------------------------------------------------------------------

    def check_frame(self, frame: RadarFrame) -> np.ndarray:
        """Check what odometry takes from ``frame`` besides the radar points, so that nothing
        non-finite can reach kiss-icp (whose Sophus aborts the whole process on it): integer
        timestamps, a rigid ``world_from_ego`` (ground truth, the first frame's initial pose) and
        a rigid ``ego_from_sensor`` for every sweep (:func:`~radarslam.geometry.rigid_problem`).
        :class:`DataError` naming the scene, timestamp and channel otherwise.

        Returns ``world_from_ego`` as float64 (float32 input is converted, not kept)."""
        if not isinstance(frame, RadarFrame):
            raise TypeError(f"odometry expects a RadarFrame, got {type(frame).__name__}")
        if not _is_int_us(frame.timestamp_us):
            raise DataError(
                f"{_where(frame)}: timestamp_us must be integer microseconds, got "
                f"{type(frame.timestamp_us).__name__} {frame.timestamp_us!r}"
            )
        gt = frame.world_from_ego
        why = rigid_problem(gt)
        if why is not None:
            raise DataError(f"{_where(frame)}: world_from_ego {why}")
        gt = np.asarray(gt, dtype=np.float64)  # no copy for float64
        for ch, sweep in frame.sweeps.items():
            self._check_sweep(frame, ch, sweep)
        return gt

    def _check_sweep(self, frame: RadarFrame, ch: str, sweep) -> None:
        """One sweep's timestamp and calibration (a set lookup once its calibration was seen)."""
        cal = sweep.ego_from_sensor
        key = (cal.dtype.str, cal.tobytes()) if isinstance(cal, np.ndarray) else None
        if key in self._good_calibrations and _is_int_us(sweep.timestamp_us):
            return
        if not _is_int_us(sweep.timestamp_us):
            raise DataError(
                f"{_where(frame)}: {ch} sweep timestamp_us must be integer microseconds, got "
                f"{type(sweep.timestamp_us).__name__} {sweep.timestamp_us!r}"
            )
        why = rigid_problem(cal)
        if why is not None:
            raise DataError(f"{_where(frame)}: {ch} ego_from_sensor {why}")
        if key is not None and len(self._good_calibrations) < _MAX_CALIBRATIONS:
            self._good_calibrations.add(key)

    def calibrated_frame(self, frame: RadarFrame) -> RadarFrame:
        """``frame`` as the odometry uses it: the mounting yaws given (``mounting_yaw_deg``) and
        folded in at resets added to its sweeps' calibration."""
        return with_mounting(frame, self._mounting)

    # --- points -------------------------------------------------------------------------------

    def ego_points(self, frame: RadarFrame, fit: EgoMotionFit, twist: np.ndarray) -> np.ndarray:
        """(M, 3) dynamic-free points of all radars in the ego frame at ``frame.timestamp_us``,
        de-skewed with ``twist`` and lifted to z = 0.

        Each sweep's timestamp and ``ego_from_sensor`` are checked as in :meth:`check_frame` (a
        set lookup once a calibration was seen), so a bad one cannot make non-finite points."""
        pc = self.config.points
        # All radars' points in one set of arrays, each point with its sweep's transform: one
        # numpy call per step instead of one per step and radar.
        sweeps, rots, trans = [], [], []
        for ch, sweep in frame.sweeps.items():
            if len(sweep) == 0:
                continue
            self._check_sweep(frame, ch, sweep)
            ego_from_sensor = sweep.ego_from_sensor
            if pc.deskew:
                dt_s = (sweep.timestamp_us - frame.timestamp_us) * 1e-6
                ego_from_sensor = exp_se2(twist * dt_s) @ ego_from_sensor
            sweeps.append((ch, sweep))
            rots.append(ego_from_sensor[:2, :2])
            trans.append(ego_from_sensor[:2, 3])
        if not sweeps:
            return np.zeros((0, 3))
        x, y = (
            np.concatenate([sw.points[name] for _, sw in sweeps]).astype(np.float64)
            for name in ("x", "y")
        )
        rng = np.hypot(x, y)
        keep = np.isfinite(rng) & (rng >= pc.min_range_m) & (rng <= pc.max_range_m)
        if pc.dynamic_free and fit.valid:
            keep &= np.concatenate(
                [fit.static_masks.get(ch, np.zeros(len(sw), dtype=bool)) for ch, sw in sweeps]
            )
        of = np.repeat(np.arange(len(sweeps)), [len(sw) for _, sw in sweeps])[keep]
        rot, t = np.array(rots)[of], np.array(trans)[of]
        x, y = x[keep], y[keep]
        out = np.zeros((len(x), 3))
        out[:, 0] = x * rot[:, 0, 0] + y * rot[:, 0, 1] + t[:, 0]
        out[:, 1] = x * rot[:, 1, 0] + y * rot[:, 1, 1] + t[:, 1]
        return out

    # --- main step ----------------------------------------------------------------------------

    def process(self, frame: RadarFrame) -> OdometryResult:
        """One frame: the Doppler fit, its static points, the prediction, the registration
        fused into it, the relative motion and the key-frame bookkeeping (module docstring)."""
        t0 = time.perf_counter()
        # Before anything uses the frame: a NaN pose given to kiss-icp aborts the process.
        ground_truth = self.check_frame(frame)
        self._track_rig(frame)
        frame = self.calibrated_frame(frame)
        fit = self.doppler.fit_frame(
            frame,
            self._twist_bounds(frame.timestamp_us),
            mounting_residuals=self._residuals,
            twist_rate=None if self._rate is None else self._rate.rate(frame.timestamp_us),
        )
        t1 = time.perf_counter()
        motion = self._frame_twist(frame, fit)
        points = self.ego_points(frame, fit, motion.twist)
        t2 = time.perf_counter()
        first = self._pose is None
        pred = self._first_pose(ground_truth) if first else self._predict(fit, motion)
        if not first:
            pred = self._residual_calibration(fit, pred)
        reg = self._register(points, pred, motion, fit, first)
        t3 = time.perf_counter()
        relative, rel_cov, turn_cov = self._relative_motion(pred, reg, motion, first)
        is_key_frame, kf_motion, kf_cov = self._key_frame(
            frame, pred, reg, relative, turn_cov, first
        )
        self._advance(frame, fit, motion, reg, relative, first)
        t4 = time.perf_counter()
        return OdometryResult(
            timestamp_us=int(frame.timestamp_us),
            world_from_ego=reg.pose.copy(),
            pose_covariance=reg.cov.copy(),
            relative_motion=relative,
            relative_covariance=rel_cov,
            doppler=fit,
            registration=reg.result,
            icp_accepted=reg.accepted,
            status=reg.status,
            num_points=len(points),
            timing=FrameTiming(
                doppler_ms=(t1 - t0) * 1e3,
                points_ms=(t2 - t1) * 1e3,
                registration_ms=(t3 - t2) * 1e3,
                total_ms=(t4 - t0) * 1e3,
            ),
            ground_truth=ground_truth,
            is_key_frame=is_key_frame,
            sample_token=frame.sample_token,
            scene_name=frame.scene_name,
            key_frame_motion=kf_motion,
            key_frame_covariance=kf_cov,
        )

    def _track_rig(self, frame: RadarFrame) -> None:
        """The frame's radar rig (chosen at a segment's first frame with sweeps) and its scenes."""
        if self._rig_pending:
            self._select_rig(frame)
        elif self._rig is not None:
            self._rig.learn(frame)
        if self._rig is not None and frame.scene_name:
            scenes = self._rig.scenes
            if (not scenes or scenes[-1] != frame.scene_name) and frame.scene_name not in scenes:
                scenes.append(frame.scene_name)

    def _frame_twist(self, frame: RadarFrame, fit: EgoMotionFit) -> _FrameTwist:
        """Twist of this frame: the fit, or the last one held (its uncertainty growing)."""
        if self._t_us is not None and frame.timestamp_us <= self._t_us:
            raise DataError(
                f"frame at {frame.timestamp_us} us (scene {frame.scene_name or '?'}) is not after "
                f"the previous one ({self._t_us} us): frames must be in time order"
            )
        gap_s = 0.0 if self._t_us is None else (frame.timestamp_us - self._t_us) * 1e-6
        stopped = False
        if fit.valid:
            twist = fit.twist
            twist_cov = _sym(fit.covariance) * self.config.fusion.doppler_cov_scale
            # The zero-velocity test asks whether this fit's twist is told from 0; the floor
            # below models errors shared across frames, and would call a creeping car stopped.
            if fit.ego_static and _chi2(twist, twist_cov) < _ZERO_VELOCITY_CHI2:
                # Zero-velocity update: the static rule fired and the refitted twist cannot be
                # told from 0, so integrating its noise would only add drift.
                twist = np.zeros(3)
                stopped = True
            twist_cov = twist_cov + self._twist_floor
        else:
            twist = self._twist.copy()
            twist_cov = self._twist_cov + self._growth * max(gap_s, 1e-3)
        if not np.all(np.isfinite(twist)) or not np.all(np.isfinite(twist_cov)):
            twist, twist_cov = self._twist.copy(), self._twist_cov + self._growth
        return _FrameTwist(twist, twist_cov, stopped, gap_s)

    def _first_pose(self, ground_truth: np.ndarray) -> _Prediction:
        """A segment's first frame: a new map, the initial pose, known exactly."""
        self._registration = self._new_registration()
        cfg = self.config
        pose = planar(ground_truth) if cfg.initial_pose == "ground_truth" else np.eye(4)
        return _Prediction(pose, np.zeros((3, 3)), np.eye(4), np.zeros((3, 3)), None)

    def _predict(self, fit: EgoMotionFit, motion: _FrameTwist) -> _Prediction:
        """The filter's prediction: the two frames' twists (trapezoid) integrated over the gap,
        corrected by the calibration states, and the covariances carried along."""
        gap_s = motion.gap_s
        xi, xi_calib = self._calibrated(
            0.5 * (self._twist + motion.twist) * gap_s, gap_s, fit.mounting_jacobian
        )
        delta = exp_se2(xi)
        jr = exp_jacobian_twist(xi)
        # Twist random walk (q per second) integrated over the interval: q dt^3.
        xi_cov = 0.25 * (self._twist_cov + motion.cov) * gap_s**2
        if not fit.valid and self._last_fit is not None:
            # A held twist errs by one error for the whole hold, not by a fresh one each
            # frame: from its last fit's covariance C0 and the growth G, the pose has drifted
            # by C0 T^2 + G T^3 / 3 after T s (this interval adds the difference). Counted
            # frame by frame, a 1 s hold claimed a third of the sigma, and the registration
            # could not pull back the along-track error that braking through it left.
            assert self._t_us is not None
            _, c0, since_us = self._last_fit
            a = (self._t_us - since_us) * 1e-6
            b = a + gap_s
            xi_cov = c0 * (b**2 - a**2) + self._growth * ((b**3 - a**3) / 3.0)
        both_stopped = motion.stopped and self._stopped
        if not both_stopped:
            # A vehicle stopped at both ends of a 77 ms interval did not accelerate in it.
            xi_cov = xi_cov + self._q * gap_s**3
        delta_cov = jr @ xi_cov @ jr.T
        ad = adjoint_se2(invert(delta))
        assert self._pose is not None
        pose = self._pose @ delta
        jc = jr @ xi_calib  # pose error per calibration error
        self._calib_cov = self._calib_cov + self._calib_q * gap_s
        pose_cov = _sym(
            ad @ self._cov @ ad.T
            + ad @ self._cross @ jc.T
            + jc @ self._cross.T @ ad.T
            + jc @ self._calib_cov @ jc.T
            + delta_cov
        )
        self._cross = ad @ self._cross + jc @ self._calib_cov
        if not both_stopped:
            # (standing, the pose is held exactly: nothing moves it against the map)
            self._unregistered_cov = _sym(ad @ self._unregistered_cov @ ad.T + delta_cov)
        return _Prediction(pose, pose_cov, delta, delta_cov, jc)

    def _residual_calibration(self, fit: EgoMotionFit, pred: _Prediction) -> _Prediction:
        """The mounting yaws updated by the Doppler residuals' information
        (``calibration.residual_cov_scale``) in the directions the frame's twist does not show;
        the pose follows through its correlation with them.

        Information form, since the residuals leave some directions unobserved (a rotation
        common to all radars): with Lambda the yaws' information and eta its vector, both
        projected onto the null space of the twist's mounting Jacobian J, the Kalman update is
        dx = P H^T (Lambda C + I)^-1 (eta - Lambda m), P -= P H^T (Lambda C + I)^-1 Lambda H P,
        C = H P H^T the yaws' covariance, m their estimate."""
        scale = self.config.fusion.calibration.residual_cov_scale
        if not self._residuals or scale is None or not fit.valid:
            return pred
        info, vector = fit.mounting_information, fit.mounting_information_vector
        if not np.any(info):
            return pred
        n = len(RADAR_CHANNELS)
        jac = fit.mounting_jacobian
        jjt = jac @ jac.T
        eps = 1e-9 * max(float(np.trace(jjt)), 1e-300)
        proj = np.eye(n) - jac.T @ np.linalg.solve(jjt + eps * np.eye(3), jac)
        lam = proj @ info @ proj / scale
        eta = proj @ vector / scale
        ph_pose = self._cross[:, :n]  # P H^T, pose rows
        ph_cal = self._calib_cov[:, :n]  # P H^T, calibration rows
        a = lam @ ph_cal[:n] + np.eye(n)
        sol = np.linalg.solve(a, np.column_stack([eta - lam @ self._calib[:n], lam]))
        step, gain_t = sol[:, 0], sol[:, 1:]  # (Lambda C + I)^-1 (eta - Lambda m), ... Lambda
        pose = planar(pred.pose @ exp_se2(ph_pose @ step))
        cov = _sym(pred.cov - ph_pose @ gain_t @ ph_pose.T)
        self._calib = self._calib + ph_cal @ step
        self._cross = self._cross - ph_pose @ gain_t @ ph_cal.T
        self._calib_cov = _sym(self._calib_cov - ph_cal @ gain_t @ ph_cal.T)
        return dataclasses.replace(pred, pose=pose, cov=cov)

    def _register(
        self,
        points: np.ndarray,
        pred: _Prediction,
        motion: _FrameTwist,
        fit: EgoMotionFit,
        first: bool,
    ) -> _Registered:
        """The points registered against the local map from the prediction and fused into it
        (unless the vehicle stands or too few points are left), then inserted at the result."""
        cfg = self.config
        pose, pose_cov = pred.pose, pred.cov
        reg_result: RegistrationResult | None = None
        status = "first" if first else "doppler"
        accepted = False
        icp_cov = None
        reg = self._registration
        if not first and motion.stopped and self._stopped:
            # Stopped at both ends (zero-velocity update): the pose is held. Registering would
            # only feed the registration's jitter back into the map, letting both wander.
            status = "stopped"
        elif reg is not None and len(points):
            source, frame_down = reg.voxelize(points)
            predicted = pose
            if not first and not reg.empty and len(source) >= cfg.registration.min_source_points:
                seed = self._registration_seed(predicted, motion.gap_s)
                reg_result = self._align(reg, source, seed)
                icp_cov = _sym(reg_result.covariance) * cfg.fusion.icp_cov_scale
                frac = cfg.fusion.icp_along_track_sigma_fraction
                if frac is not None and fit.valid:
                    # kept for the key-frame covariances too: along track, ICP adds nothing
                    icp_cov = icp_cov + along_track_covariance(pred.delta, frac)
                pose, pose_cov, accepted, status = self._fuse(
                    predicted, pose_cov, reg_result, icp_cov
                )
            elif not first:
                status = "skipped"
            reg.update(frame_down, pose)
        elif reg is not None and not first:
            status = "skipped"
        if not accepted:
            icp_cov = None
        else:
            self._unregistered_cov = np.zeros((3, 3))
        return _Registered(pose, pose_cov, reg_result, accepted, icp_cov, status)

    def _relative_motion(
        self, pred: _Prediction, reg: _Registered, motion: _FrameTwist, first: bool
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        """Motion since the previous frame, its covariance (dead reckoning fused with the two
        endpoints' registrations, plus the turn term) and the turn term alone."""
        if first:
            return np.eye(4), np.zeros((3, 3)), None
        assert self._pose is not None
        if reg.accepted and self._last_icp_cov is not None and reg.icp_cov is not None:
            rel_cov = _fuse_cov(pred.delta_cov, self._last_icp_cov + reg.icp_cov)
        else:
            rel_cov = pred.delta_cov
        relative = invert(self._pose) @ reg.pose
        turn_rate = abs(0.5 * (self._twist[2] + motion.twist[2]))
        turn_cov = self._turn_q * (turn_rate**2 * motion.gap_s)
        return relative, rel_cov + turn_cov, turn_cov

    def _key_frame(
        self,
        frame: RadarFrame,
        pred: _Prediction,
        reg: _Registered,
        relative: np.ndarray,
        turn_cov: np.ndarray | None,
        first: bool,
    ) -> tuple[bool, np.ndarray | None, np.ndarray | None]:
        """Whether this frame is a key frame, and then its motion and covariance since the
        previous one (None at a segment's first)."""
        kf_motion = kf_cov = None
        if not first:
            assert pred.calib_jacobian is not None and turn_cov is not None
            self._kf.propagate(relative, pred.delta_cov, pred.calib_jacobian, turn_cov)
        is_key_frame = bool(frame.is_key_frame)
        if is_key_frame and self._kf_started and self.key_frame_gate is not None:
            is_key_frame = self.key_frame_gate.keeps(
                invert(self._kf.anchor_pose) @ reg.pose,
                (frame.timestamp_us - self._kf.anchor_us) * 1e-6,
            )
        if is_key_frame:
            icp_cov = reg.icp_cov if reg.accepted else None
            if self._kf_started:
                kf_motion, kf_cov = self._kf.relative(reg.pose, icp_cov, self._calib_cov)
            self._kf.reset(
                reg.pose, icp_cov if reg.accepted or first else None, int(frame.timestamp_us)
            )
            self._kf_started = True
        return is_key_frame, kf_motion, kf_cov

    def _advance(
        self,
        frame: RadarFrame,
        fit: EgoMotionFit,
        motion: _FrameTwist,
        reg: _Registered,
        relative: np.ndarray,
        first: bool,
    ) -> None:
        """The filter's state moves on to this frame."""
        self._pose, self._cov = reg.pose, reg.cov
        if first:
            self._cross = np.zeros((3, len(self._calib)))
        self._t_us = frame.timestamp_us
        self._fused_yaw_rate = None if first else float(log_se2(relative)[2]) / motion.gap_s
        self._twist, self._twist_cov = motion.twist, motion.cov
        if fit.valid:
            self._last_fit = (fit.twist, motion.cov, int(frame.timestamp_us))
            if self._rate is not None:
                self._rate.add(int(frame.timestamp_us), fit.twist)
        self._stopped = motion.stopped
        self._last_icp_cov = reg.icp_cov

    def _align(
        self, reg: ScanToMapRegistration, source: np.ndarray, seed: np.ndarray
    ) -> RegistrationResult:
        """The registration from ``seed``, searched over yaw where the motion since the last
        accepted registration leaves the yaw uncertain (``registration.yaw_search_sigma_deg``)."""
        rc = self.config.registration
        sigma = float(np.sqrt(max(self._unregistered_cov[2, 2], 0.0)))
        if rc.yaw_search_sigma_deg is None or sigma <= np.deg2rad(rc.yaw_search_sigma_deg):
            return reg.align(source, seed)
        half = min(3.0 * sigma, _YAW_SEARCH_MAX_RAD)
        return reg.align_over_yaw(source, seed, half, np.deg2rad(rc.yaw_search_step_deg))

    def _registration_seed(self, predicted: np.ndarray, gap_s: float) -> np.ndarray:
        """The registration's initial pose (``registration.seed_yaw_rate``): the Doppler
        prediction, with ``odometry`` its motion since the previous frame turned at the previous
        frame's fused yaw rate instead of the Doppler's (kiss-icp's constant-velocity model, for
        the rotation only)."""
        rate = self._fused_yaw_rate
        if (
            self.config.registration.seed_yaw_rate == "doppler"
            or rate is None
            or self._pose is None
        ):
            return predicted
        xi = log_se2(invert(self._pose) @ predicted)
        xi[2] = rate * gap_s
        return planar(self._pose @ exp_se2(xi))

    def _calibrated(
        self, raw: np.ndarray, dt_s: float, mounting_jacobian: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """The Doppler motion ``raw`` (x, y, yaw over ``dt_s``) corrected by the estimated
        calibration, and its Jacobian with respect to the calibration (3 x states)."""
        model = self.config.fusion.calibration.yaw_bias_model
        jac = np.zeros((3, len(self._calib)))
        if model == "none":
            return raw, jac
        if model == "mounting":
            jac[:, :-1] = mounting_jacobian * dt_s
        else:
            jac[2, 0] = -(raw[0] if model == "per_metre" else dt_s)
        jac[0, -1], jac[1, -1] = raw[0], raw[1]
        return raw + jac @ self._calib, jac

    def _fuse(
        self,
        predicted: np.ndarray,
        pred_cov: np.ndarray,
        reg: RegistrationResult,
        icp_cov: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray, bool, str]:
        fc = self.config.fusion
        if fc.mode == "icp":
            return reg.world_from_ego, icp_cov, True, "icp"
        innovation = log_se2(invert(predicted) @ reg.world_from_ego)
        s = pred_cov + icp_cov
        try:
            mahal = float(innovation @ solve3(s, innovation))
        except np.linalg.LinAlgError:
            mahal = np.inf
        if not np.isfinite(mahal) or (
            mahal > fc.gate_chi2 and self._rejections < fc.max_consecutive_rejections
        ):
            self._rejections += 1
            return predicted, pred_cov, False, "rejected"
        self._rejections = 0
        s_inv = inv3(s)
        gain = pred_cov @ s_inv
        pose = planar(predicted @ exp_se2(gain @ innovation))
        cov = _sym((np.eye(3) - gain) @ pred_cov)
        if self.config.fusion.calibration.yaw_bias_model != "none":
            gain_c = self._cross.T @ s_inv  # the calibration rows of the Kalman gain
            self._calib = self._calib + gain_c @ innovation
            self._calib_cov = _sym(self._calib_cov - gain_c @ self._cross)
            self._cross = (np.eye(3) - gain) @ self._cross
        return pose, cov, True, "fused"
