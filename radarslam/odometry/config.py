"""Configuration of the radar odometry front end (``radarslam/configs/odometry/*.yaml``)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, field_validator, model_validator

from radarslam.config import StrictModel
from radarslam.odometry.doppler import DopplerConfig
from radarslam.types import check_radar_channel

#: A non-negative float, and three of them: (x, y, yaw) noise terms of the SE(2) fusion.
NonNegative = Annotated[float, Field(ge=0, allow_inf_nan=False)]
Triple = tuple[NonNegative, NonNegative, NonNegative]
Positive = Annotated[float, Field(gt=0, allow_inf_nan=False)]


class PointsConfig(StrictModel):
    """Which points enter registration, and the reader's state filters."""

    min_range_m: float = Field(1.0, ge=0, le=1000)
    max_range_m: float = Field(100.0, gt=0, le=1000)
    #: Keep only Doppler inliers (static world) for registration.
    dynamic_free: bool = True
    #: De-skew each radar's points to the frame's common time with the Doppler motion.
    deskew: bool = True
    #: Reader filters (None = no filter on that field). dyn_prop is not filtered: the Doppler
    #: inlier test decides what is static, and the sensor's "stopped" class is static too.
    invalid_states: list[int] | None = Field(default_factory=lambda: [0])
    dynprop_states: list[int] | None = None
    ambig_states: list[int] | None = Field(default_factory=lambda: [3])

    @field_validator("invalid_states", "dynprop_states", "ambig_states")
    @classmethod
    def _ars408_states(cls, v: list[int] | None, info) -> list[int] | None:
        # a state the sensor never reports would keep no point at all
        top = {"invalid_states": 17, "dynprop_states": 7, "ambig_states": 4}[info.field_name]
        bad = [s for s in v or [] if not 0 <= s <= top]
        if bad:
            raise ValueError(f"state {bad[0]} is not one the ARS408 reports (0-{top})")
        return v

    @model_validator(mode="after")
    def _range_order(self) -> PointsConfig:
        if self.min_range_m >= self.max_range_m:
            raise ValueError(
                f"min_range_m ({self.min_range_m}) must be below max_range_m "
                f"({self.max_range_m}): no point would be kept"
            )
        return self


class RegistrationConfig(StrictModel):
    """Scan-to-map registration against kiss-icp's voxel-hash local map: kiss-icp's own C++
    point-to-point alignment and a point-to-local-mean refinement."""

    enabled: bool = True
    voxel_size_m: float = Field(1.0, gt=0, le=1000)
    max_points_per_voxel: int = Field(20, ge=1)
    #: When kiss-icp's point-to-point alignment runs before the refinement: "always", or
    #: "fallback", only where the refinement cannot start (fewer than 3 scan points at the seed
    #: have all their ``line_neighbors`` map points within reach: a map's first frames, sparse
    #: surroundings), elsewhere the refinement alone from the Doppler seed (with
    #: ``refine_iterations: 8``). Measured, fallback against always (bench/odometry.py):
    #: 10 % fewer instructions (callgrind); real median pooled ATE over 5 Doppler seeds 0.109 m
    #: both; scene-0916's Doppler heading refitted with the estimated mounting yaws 6.0 deg off
    #: in 19.9 s, past the 0.3 deg/s bound (always: 5.9); synthetic subset / long drive 0.252 /
    #: 0.331 m against 0.249 / 0.346 m; a run's poses move by up to 2 cm with the last bits of
    #: its input (always: none on the same test, test_odometry_pipeline's mounting given back).
    point_to_point: Literal["always", "fallback"] = "always"
    #: kiss-icp's iterations: they bring the seeded scan onto the right reflectors; the
    #: point-to-local-mean refinement below does the fine alignment.
    max_num_iterations: int = Field(5, ge=1)
    convergence_criterion: float = Field(1e-4, gt=0)
    #: kiss-icp's kernel sigma (fixed); correspondences up to 3 sigma. The Doppler seed is within
    #: a few cm, so a wide window only admits wrong matches.
    fixed_sigma_m: float = Field(0.7, gt=0, le=1000)
    #: The registration's initial yaw. "odometry": the Doppler-predicted pose turned instead at
    #: the yaw rate of the previous frame's fused motion (kiss-icp's constant-velocity model for
    #: the rotation; the translation stays the Doppler's, whose distance is good to 0.1 %).
    #: "doppler": the Doppler prediction as is. In fast real turns the Doppler yaw rate errs by
    #: up to 10 deg/s for several frames, and seeded there the registration settles in a wrong
    #: minimum beside it: real scene-0916 (25-30 deg/s turns) median ATE over 5 Doppler seeds
    #: 0.183 m against 0.207 m (the peer 0.194 m), pooled 0.124 against 0.132 m. The synthetic
    #: world's Doppler errs less in turns: city subset 0.080 against 0.075 m, long drive 1.322
    #: against 1.348 m.
    seed_yaw_rate: Literal["odometry", "doppler"] = "odometry"
    #: Fewer source points than this: registration is skipped, the Doppler motion is used.
    min_source_points: int = Field(15, ge=3)
    #: Floor of the point residual sigma in the alignment covariance.
    point_sigma_m: float = Field(0.3, gt=0, le=1000)
    #: Nearest map points per source point: line fit of the covariance, mean of the refinement.
    line_neighbors: int = Field(5, ge=2)
    #: Rebuild the KD-tree mirror of the map used for covariances every N map updates.
    mirror_every: int = Field(5, ge=1)
    #: Gauss-Newton iterations on point-to-local-mean residuals (0 = off, kiss-icp alone; see
    #: ScanToMapRegistration._refine): kiss-icp's nearest-point cost is nearly flat in yaw inside
    #: the noisy clouds of radar returns. A step below 0.1 mm and 0.006 deg ends them early
    #: (rarely: on real radar 8 steps from the seed run to the end on 4 frames in 5). Only
    #: source points whose ``line_neighbors`` nearest map points all lie within the
    #: correspondence distance take part: at the edge of the map the neighbours lie behind the
    #: point and their mean would pull the scan back.
    refine_iterations: int = Field(3, ge=0)
    #: Largest Aitken extrapolation of a refinement step (1 = plain Gauss-Newton): the local-mean
    #: target moves with the point, so plain steps shrink geometrically.
    refine_max_extrapolation: float = Field(8.0, ge=1.0)
    #: Where the yaw of the motion since the last accepted registration is uncertain by more
    #: than this (1 sigma; after the twist was held through an outage), the registration is
    #: seeded at yaw offsets over +-3 sigma (at most +-20 deg, yaw_search_step_deg apart); an
    #: alignment that matches more than 2 source points more than the one from the usual seed
    #: replaces it (of those, the one with the lowest residual). A registration's yaw barely
    #: leaves its seed: after a 1 s outage ending a real 84 deg turn (scene-0916) the held yaw
    #: rate had turned the pose 8 deg too far, and seeded there the scan stayed 8 deg off for
    #: good. None: off.
    yaw_search_sigma_deg: float | None = Field(1.5, gt=0)
    yaw_search_step_deg: float = Field(1.5, gt=0, le=10)


class CalibrationConfig(StrictModel):
    """Doppler calibration states of the fusion filter, observed through the registration.

    A radar mounted a fraction of a degree off its nominal yaw turns its Doppler velocities, and
    the joint fit reads the difference between radars as a yaw rate proportional to speed: on
    real nuScenes the fit's yaw rate is 1.3 deg/s too high at 5-6 m/s on a Singapore scene
    (scene-0916: 23 deg of heading lost in 20 s), whose radars measure 0.2-1.0 deg off nominal.
    The Doppler alone cannot tell a differential mounting error from a yaw rate, so the filter
    carries the calibration as states, predicted through the Doppler fit's derivative with
    respect to each radar's mounting yaw and corrected by every accepted registration. With
    "mounting" the Doppler heading over scene-0916, refitted with the estimated mounting yaws,
    is 6 deg off instead of 23 and every other real scene's within 0.5 deg; the estimate is
    reported in the run's summary (``doppler_calibration``) and can be given back as
    ``mounting_yaw_deg``. Each radar rig (its nominal extrinsics) has its own states: scenes of
    several cars in one run do not share them. Real pooled ATE (bench/odometry.py, median over 5
    Doppler seeds): none 0.133 m, rate 0.130 m, per_metre 0.129 m, mounting 0.124 m."""

    #: "mounting": one mounting-yaw error per radar (rad, RADAR_CHANNELS order);
    #: "per_metre": a yaw-rate bias proportional to the forward speed (rad per metre travelled);
    #: "rate": a constant yaw-rate bias (rad/s); "none": no calibration states.
    yaw_bias_model: Literal["none", "rate", "per_metre", "mounting"] = "mounting"
    #: Prior sigma of each yaw state (rad with "mounting", rad/m with "per_metre", rad/s with
    #: "rate"): 1 deg, the order of real mounting errors.
    yaw_bias_prior: float = Field(0.0175, gt=0, le=10)
    #: Random walk of each yaw state per sqrt(second) (0: a constant, as a mounting is).
    yaw_bias_walk: float = Field(0.0, ge=0, le=10)
    #: Prior sigma of a Doppler speed-scale error (fraction; 0 = not estimated). Off: the
    #: registration's along-track pull (see icp_along_track_sigma_fraction) leaks into it as a
    #: false scale (synthetic city ATE 0.031 -> 0.076 m with 0.01), while the Doppler path
    #: length is 0.997-1.000 of the truth on the real scenes.
    speed_scale_prior: float = Field(0.0, ge=0, le=1)
    #: Random walk of the speed-scale error per sqrt(second).
    speed_scale_walk: float = Field(0.0, ge=0, le=1)
    #: 2: a self-calibration pass. ``run_odometry`` runs the scenes once (every
    #: ``pass_frame_stride``-th frame), then again with the mounting yaws the first pass
    #: estimated applied to every sweep from its first frame (as ``mounting_yaw_deg`` does); the
    #: filter estimates what is left, and neither the map nor the early Doppler fits carry the
    #: error while it converges. Real pooled ATE (bench/odometry.py, median over 5 Doppler
    #: seeds) 0.109 m against 0.124 m with one pass, at 1.2x its CPU with reading (the
    #: calibrated second pass registers faster). With ``yaw_bias_model: mounting`` only, and one
    #: rig: over scenes of several cars the single pass's per-rig estimates are kept (a warning
    #: says so).
    passes: int = Field(2, ge=1, le=2)
    #: The first pass runs on every k-th frame only: the calibration needs the drive's turns
    #: and speeds, not every frame. Real pooled ATE (Doppler seed 0) with strides 1 / 2 / 3 / 4
    #: / 6 / 8 / 10: 0.111 / 0.111 / 0.111 / 0.106 / 0.109 / 0.107 / 0.216 m (at 10 the pass's
    #: frames are 0.75 s apart and scene-0916's turns lose the registration); with
    #: RADAR_BACK_LEFT silent (bench/degraded.py) 4 put scene-0061 at 0.242 m, 3 at 0.069 m.
    pass_frame_stride: int = Field(3, ge=1, le=8)
    #: At every reset (a new scene or segment, each SLAM session) the mounting yaws estimated so
    #: far for the rig are applied to its later sweeps, as ``mounting_yaw_deg`` does, and the
    #: states start again from zero with their covariance kept: the next scene's map and Doppler
    #: fits start calibrated instead of waiting for the filter. The reported estimate stays the
    #: total.
    fold_at_reset: bool = True
    #: Each frame's Doppler residuals also observe the mounting yaws (each radar's inliers
    #: against the joint fit), where the registration sees only what moves the Doppler twist:
    #: two units that look the same way from about the same place (nuScenes' rear corner units)
    #: turned opposite ways leave the twist as it is. With a value, that residual information,
    #: its covariance scaled by this (one target set's residuals repeat from frame to frame),
    #: updates the yaws in the directions the frame's twist does not show (the null space of its
    #: mounting Jacobian), with the registration only. At 100 the real scenes' estimates agree
    #: with a fit of each radar's yaw to the ground truth's motion to 0.15 deg RMS instead of
    #: 0.40 (a rotation common to all radars aside). What it buys is a better calibration
    #: pass: real pooled ATE with the pass 0.109 m, 0.114 m without the residuals (medians
    #: over 5 Doppler seeds); in a single pass it gains nothing (0.126 against 0.127 m) and the
    #: Doppler fit refitted with its yaws drifts 0.33 deg/s on scene-0916. None: off.
    residual_cov_scale: float | None = Field(100.0, gt=0)
    #: A turn that all radars share turns the Doppler velocity and the scans alike: the
    #: registration then agrees with the Doppler in a turned vehicle frame, so no radar
    #: measurement observes it (five real scenes given a 1 deg turn of every radar keep it in
    #: their estimate, ATE unchanged), and the car's heading carries whatever the estimate
    #: holds. The filter's prior spreads one radar's error over all five: with one unit 3 deg
    #: out of line (bench/degraded.py) the shared part came out 0.6-2.3 deg off, the key-frame
    #: motions crabbed sideways (NEES 6.2-13.8). "median": the calibration pass's estimate is
    #: applied with its median taken out, i.e. most units sit where the nominal extrinsics put
    #: them and one or two are off (with RADAR_FRONT 3 deg off NEES 4.6 and RPE per 10 m
    #: 0.140 m instead of 13.8 and 0.270 m; the clean split's median ATE over 5 Doppler seeds
    #: 0.109 m either way). "filter": the estimate as the filter leaves it (SLAM's preset:
    #: docs/results.md, settings table).
    common_yaw: Literal["median", "filter"] = "median"


class FusionConfig(StrictModel):
    """Error-state Kalman filter on SE(2): Doppler drives the prediction, ICP is the measurement."""

    #: "kalman": the fusion below; "doppler": dead reckoning only (no registration);
    #: "icp": take the registration as is whenever it ran (Doppler only seeds it).
    mode: Literal["kalman", "doppler", "icp"] = "kalman"
    #: Mahalanobis gate on the ICP innovation (chi-square, 3 dof). Real innovations are heavy
    #: tailed: 0.5-0.9 % of real frames exceed the Gaussian 99.9 % point (16.27), and where a
    #: fast turn's Doppler yaw rate errs by up to 10 deg/s for several frames, rejecting the
    #: registration there let the error into the map (scene-0916: 0.55-0.72 m ATE on 2 of 6
    #: Doppler RANSAC seeds, 0.17-0.21 m at 40; docs/results.md).
    gate_chi2: float = Field(40.0, gt=0)
    #: After this many consecutive rejections ICP is accepted again (re-localise in the map).
    max_consecutive_rejections: int = Field(10, ge=1)
    #: Scale of the registration covariance: the point-to-line Hessian treats matches as
    #: independent and the map as exact, and both are false (map points carry the scan's noise,
    #: neighbouring matches are correlated, the map drifts with the poses that built it).
    icp_cov_scale: float = Field(4.0, gt=0)
    #: Scale of the Doppler fit's residual covariance: its errors are heavy-tailed and
    #: correlated from frame to frame (a target set seen for several frames), which a per-frame
    #: covariance cannot express; a larger scale weights the registration more.
    doppler_cov_scale: float = Field(8.0, gt=0)
    #: Extra ICP variance along this frame's predicted motion, as a fraction of its length (sigma =
    #: fraction x step; None = off), applied while the Doppler fit is valid. Scan-to-map matching
    #: is biased along the direction of travel (the local map is dense behind the scan and
    #: sparse ahead, so nearest points and local means pull the scan back), while the Doppler
    #: speed is not: with 1.0 the along-track step comes from Doppler and the lateral and yaw
    #: corrections from ICP.
    icp_along_track_sigma_fraction: float | None = Field(1.0, gt=0, le=1000)
    #: The five radars sweep tens of ms apart: the joint Doppler fit reads each sweep at its own
    #: time, the twist carried there by its rate of change over the valid fits of the last this
    #: many seconds (``TwistRate``). None: every sweep taken at the frame's time, where braking
    #: or speeding up reads as turning (left and right units see different speeds). Real split,
    #: Doppler seed 0, pooled ATE / RPE per 10 m: 0.109 / 0.123 m at 0.5, 0.108 / 0.128 at 0.3,
    #: 0.111 / 0.127 at 1.0, 0.111 / 0.124 with None.
    twist_rate_window_s: float | None = Field(0.5, gt=0, le=10)
    #: Standard deviation added to every Doppler twist (forward m/s, lateral m/s, rad/s), after
    #: the scaling above: on real radar the fit's residual covariance misses errors that persist
    #: across frames (velocities quantised at 0.25 m/s, one target set seen for several frames,
    #: mounting errors).
    twist_sigma_floor: Triple = (0.2, 0.1, 0.02)
    #: Error shared by the Doppler fit and the registration while turning, (m, m, rad) per
    #: sqrt(second) per rad/s of yaw rate: the five radars fire at different times and de-skew,
    #: lever arms and side slip all err in proportion to the turn rate, in both sources alike, so
    #: fusing them does not average it out. Added to the reported relative-motion and key-frame
    #: covariances (not to the filter's, whose gate compares the two sources). On the real
    #: scenes' turns (over 9 deg/s) the key-frame NEES is 17 without it.
    turn_sigma_per_radps: Triple = (0.1, 0.2, 0.02)
    #: Random walk of the twist between Doppler fits, (m/s, m/s, rad/s) per sqrt(second): covers
    #: acceleration while the radars fire at different times within a frame.
    process_noise: Triple = (0.2, 0.2, 0.02)
    #: Twist variance added per second while the Doppler fit is invalid (constant velocity held).
    invalid_doppler_growth: Triple = (1.0, 1.0, 0.05)
    #: Largest change of the Doppler twist per second since the last valid fit (forward m/s^2,
    #: lateral m/s^2, rad/s^2; None = any): the fit considers only twists within it, and a frame
    #: with none is invalid (the twist is held). About twice what consecutive real fits differ
    #: by at most (0.6 m/s, 0.7 m/s, 0.44 rad/s over 75 ms, fast turns and fit noise included).
    #: Where only a few radars report, a moving car alongside can outvote the static world: on
    #: real scene-0061 with RADAR_FRONT silent, one frame of the two front corner units fitted
    #: 273 deg/s and the scene's ATE was 2.84 m (0.16 m with the bound).
    max_twist_rate: tuple[Positive, Positive, Positive] | None = (20.0, 20.0, 10.0)
    calibration: CalibrationConfig = Field(default_factory=CalibrationConfig)
    #: Segments of a multi-scene run restart (from initial_pose) after a gap longer than this.
    max_gap_s: float = Field(1.0, gt=0)

    @field_validator(
        "process_noise",
        "invalid_doppler_growth",
        "twist_sigma_floor",
        "turn_sigma_per_radps",
        "max_twist_rate",
        mode="before",
    )
    @classmethod
    def _three_values(cls, value):
        if isinstance(value, (list, tuple)) and len(value) != 3:
            raise ValueError(f"expected 3 values (x, y, yaw), got {len(value)}")
        return value


class OdometryConfig(StrictModel):
    """The whole front end. ``initial_pose``: the first frame's pose is its ground-truth
    ``world_from_ego`` (so estimates live in the nuScenes global frame), or the identity."""

    initial_pose: Literal["ground_truth", "identity"] = "ground_truth"
    doppler: DopplerConfig = Field(
        default_factory=lambda: DopplerConfig(
            static_velocity="refit",
            min_points=4,
            speed_scale_error=-0.003,
            fallback_lateral_velocity_sigma_mps=0.2,
        )
    )
    points: PointsConfig = Field(default_factory=PointsConfig)
    registration: RegistrationConfig = Field(default_factory=RegistrationConfig)
    fusion: FusionConfig = Field(default_factory=FusionConfig)
    #: Known mounting-yaw errors (deg, per radar channel) added to every sweep's nominal
    #: ``calibrated_sensor`` yaw before the Doppler fit and the points use it: for instance the
    #: ``mounting_yaw_error_deg`` that a run with ``yaw_bias_model: mounting`` reported for the
    #: same car. Empty: the nominal calibration.
    mounting_yaw_deg: dict[str, float] = Field(default_factory=dict)

    @field_validator("mounting_yaw_deg")
    @classmethod
    def _mounting(cls, value: dict[str, float]) -> dict[str, float]:
        for ch, deg in value.items():
            check_radar_channel(ch)
            if not -10.0 <= deg <= 10.0:
                raise ValueError(f"{ch}: {deg} deg is not a mounting error (expected -10 to 10)")
        return value
