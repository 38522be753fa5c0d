"""Doppler ego-motion: the sensor's (or the vehicle's) velocity from radial velocities.

Measurement model. A radar measures for each target the radial (Doppler) velocity
``v_r = u . v_rel`` with ``u = (x, y) / |(x, y)|`` the line of sight in the sensor frame and
``v_rel`` the target's velocity relative to the sensor. We always take ``v_r`` from the RAW
velocity fields (``vx, vy``), never from the compensated ones (``vx_comp, vy_comp``): those
already contain an ego-motion estimate and would make the fit circular.
For a static target ``v_rel = -v_sensor``, so

    v_r = -u . v_sensor                                                    (one radar)

and with several radars rigidly mounted at ``ego_from_sensor_i = (R_i, t_i)`` on a vehicle
moving with rear-axle velocity ``v`` and yaw rate ``w`` (Kellner et al., "Instantaneous ego-motion
estimation using multiple Doppler radars", ICRA 2014):

    v_sensor_i = R_i^T (v + w x t_i),   w x t = w (-t_y, t_x)
    v_r = -(R_i u) . v - w (R_i u) . (-t_y, t_x)                           (all radars jointly)

Estimation. RANSAC over minimal sets (2 points for one radar, 3 for the joint fit) rejects moving
targets, ghosts and multipath; the consensus set is refitted by least squares (twice, re-selecting
inliers) and the covariance is the residual variance times ``(A^T A)^-1`` (the variance is floored
at ``noise_floor_mps**2`` so that a fit through few points does not claim impossible precision).

Static ego (AutoPlace's dynamic-points-removal rule): if more than ``static_fraction`` of the points
have ``|v_r| < static_speed_mps`` the vehicle is declared static, the static mask keeps those points
and the velocity is 0. At walking pace a moving vehicle also satisfies the rule, so the odometry can
ask for ``static_velocity="refit"``: the mask is the same, but the velocity is the least-squares fit
on the masked points (about 0 when truly static, the creeping speed otherwise).

Failure modes never raise: with fewer than ``min_points`` usable points, or when all usable lines of
sight are (nearly) parallel so that the velocity is not observable, the result has ``valid=False``,
zero velocity, a huge covariance and an all-False static mask (nothing is confirmed static). In
the joint fit a yaw rate that the geometry cannot observe (one radar only: its ``w x t`` column is
a combination of the other two) is held by a weak zero prior and shows up as a large yaw-rate
variance.
"""

from __future__ import annotations

import functools
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from pydantic import Field

from radarslam.config import StrictModel
from radarslam.odometry.linalg3 import inv3, solve3
from radarslam.types import RADAR_CHANNELS, RadarFrame, RadarSweep

#: Smallest eigenvalue of ``A^T A / n`` (directions only) below which the velocity is unobservable:
#: about the spread of lines of sight within +-1.8 degrees.
_MIN_DIRECTION_EIGEN = 1e-3
#: Variance reported along unobservable directions (m/s or rad/s squared).
_HUGE_VARIANCE = 1e6
#: Minimal-set determinant below which a RANSAC hypothesis is skipped (near-parallel sight lines).
_MIN_SAMPLE_DET = 0.05
#: A yaw rate whose standard deviation (at the noise floor) exceeds this is called unobservable.
_YAW_OBSERVABLE_SIGMA_RADPS = 0.5
#: The fallback lateral prior is used only where it gives the yaw rate to this (at the noise
#: floor): through a radar far ahead of the rear axle (RADAR_FRONT, 3.4 m: 0.06 rad/s at 0.2 m/s),
#: not through one beside it (a back unit, 0.6 m: 0.36 rad/s), whose mounting error alone would
#: read as tens of deg/s.
_FALLBACK_YAW_SIGMA_RADPS = 0.1


@dataclass(frozen=True)
class SensorVelocityFit:
    """One radar sweep's Doppler fit."""

    velocity_mps: np.ndarray  # (2,) sensor velocity over ground, in the sensor frame
    covariance: np.ndarray  # (2, 2)
    static_mask: np.ndarray  # (N,) bool: points consistent with a static world (inliers)
    ego_static: bool  # the static-ego rule fired
    num_inliers: int
    valid: bool  # False when too few points or degenerate geometry

    @property
    def speed_mps(self) -> float:
        return float(np.linalg.norm(self.velocity_mps))


@dataclass(frozen=True)
class EgoMotionFit:
    """All radars of a frame fitted jointly: the vehicle's planar velocity and yaw rate."""

    velocity_mps: np.ndarray  # (2,) rear-axle forward & lateral velocity in the ego frame
    yaw_rate_radps: float
    covariance: np.ndarray  # (3, 3) for (vx, vy, yaw_rate)
    static_masks: dict[str, np.ndarray]  # channel -> (N,) bool
    ego_static: bool
    num_inliers: int
    valid: bool
    num_points: int = 0  # usable points that entered the fit
    residual_rms_mps: float = float("nan")  # RMS Doppler residual of the inliers
    yaw_rate_observable: bool = True  # False when only the weak zero prior held the yaw rate
    channels: tuple[str, ...] = field(default=())
    #: (3, 5) d twist / d mounting yaw of each radar (RADAR_CHANNELS order); zeros when unknown.
    mounting_jacobian: np.ndarray = field(default_factory=lambda: np.zeros((3, 5)))
    #: What the inliers' residuals say about each radar's mounting yaw (rad, RADAR_CHANNELS
    #: order) with the twist eliminated, in information form: (5, 5) information and (5,)
    #: information vector (the estimate is information^-1 vector); zeros when unknown.
    mounting_information: np.ndarray = field(default_factory=lambda: np.zeros((5, 5)))
    mounting_information_vector: np.ndarray = field(default_factory=lambda: np.zeros(5))
    #: The time the twist holds at (us; None: the fit took every sweep as simultaneous) and the
    #: twist's rate of change (d(vx, vy, yaw rate)/dt in the body frame) the fit assumed to carry
    #: it to each sweep's own time.
    time_us: int | None = None
    twist_rate: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def twist_at(self, timestamp_us: int) -> np.ndarray:
        """(3,) the twist at a sweep's time (the fitted one where the fit had no time)."""
        if self.time_us is None:
            return self.twist
        return self.twist + (timestamp_us - self.time_us) * 1e-6 * self.twist_rate

    @property
    def twist(self) -> np.ndarray:
        """(3,) (vx, vy, yaw_rate)."""
        return np.array([self.velocity_mps[0], self.velocity_mps[1], self.yaw_rate_radps])


@dataclass(frozen=True)
class TwistBounds:
    """The twists a frame's fit may take: each component (vx m/s, vy m/s, yaw rate rad/s) within
    ``half_width`` of ``center`` (what the vehicle can have reached since its last fit)."""

    center: np.ndarray  # (3,)
    half_width: np.ndarray  # (3,), > 0

    def contains(self, twists: np.ndarray) -> np.ndarray:
        """Per row of ``twists`` (K, 3) (or one (3,) twist): inside the bounds."""
        return np.all(np.abs(np.asarray(twists) - self.center) <= self.half_width, axis=-1)

    def scaled(self, gain: float) -> TwistBounds:
        return TwistBounds(self.center * gain, self.half_width * abs(gain))


class TwistRate:
    """The twist's rate of change from the recent joint fits: per component, the least-squares
    slope over the fits of the last ``window_s`` (the body frame's d(vx, vy, yaw rate)/dt; a car's
    d vy/dt is about 0). What :meth:`DopplerEstimator.fit_frame` needs to read each sweep of a
    frame at its own time."""

    def __init__(self, window_s: float, min_fits: int = 3) -> None:
        self.window_us = window_s * 1e6
        self.min_fits = min_fits
        self._t: deque[float] = deque()
        self._x: deque[np.ndarray] = deque()

    def add(self, timestamp_us: int, twist: np.ndarray) -> None:
        self._t.append(float(timestamp_us))
        self._x.append(np.asarray(twist, dtype=np.float64))
        while self._t and self._t[0] < timestamp_us - self.window_us:
            self._t.popleft()
            self._x.popleft()

    def rate(self, timestamp_us: int) -> np.ndarray | None:
        """(3,) per second at ``timestamp_us``, from the fits of the window before it; None with
        fewer than ``min_fits`` of them or where they span less than half the window."""
        keep = [k for k, t in enumerate(self._t) if timestamp_us - self.window_us <= t]
        if len(keep) < self.min_fits:
            return None
        t = np.array([self._t[k] for k in keep]) * 1e-6
        if t[-1] - t[0] < 0.5 * self.window_us * 1e-6:
            return None
        x = np.stack([self._x[k] for k in keep])
        tc = t - t.mean()
        return (tc @ (x - x.mean(axis=0))) / float(tc @ tc)


class DopplerConfig(StrictModel):
    """Settings of :class:`DopplerEstimator` (the ``doppler`` section of the odometry config)."""

    #: Wider than fit_sensor_velocity's 0.2 m/s default: azimuth noise adds |v| * sin(az) * d_az to
    #: the Doppler residual at speed, and a tight threshold then truncates (and biases) the fit.
    inlier_threshold_mps: float = Field(0.4, gt=0, le=1000)
    #: Paper-style relative threshold tau: inlier if |residual| < tau * |v_sensor| (floored at
    #: ``inlier_threshold_mps``). None = absolute threshold only.
    relative_threshold: float | None = Field(None, gt=0, le=10)
    static_speed_mps: float = Field(1.0, ge=0, le=1000)
    static_fraction: float = Field(0.5, ge=0, le=1)
    static_velocity: Literal["zero", "refit"] = "zero"
    iterations: int = Field(64, ge=1, le=10000)
    min_points: int = Field(3, ge=2)
    min_range_m: float = Field(0.5, ge=0, le=1000)
    #: Drop points whose Doppler is ambiguous (``ambig_state != 3``): their v_r may be aliased.
    require_unambiguous: bool = True
    noise_floor_mps: float = Field(0.05, gt=0, le=1000)
    #: Non-holonomic prior on the rear axle's lateral velocity (m/s, None = off): a car's rear axle
    #: does not slide sideways, which makes the yaw rate observable from a single radar.
    lateral_velocity_sigma_mps: float | None = Field(None, gt=0, le=1000)
    #: The same prior for the frames whose radars alone leave the yaw rate free (one radar
    #: reporting, or several seeing along one line), where ``lateral_velocity_sigma_mps`` is None
    #: and the prior gives the yaw rate to 0.1 rad/s (a radar far enough ahead of the rear axle).
    #: None: those frames' yaw rate is held at 0 by the weak prior below.
    fallback_lateral_velocity_sigma_mps: float | None = Field(None, gt=0, le=1000)
    #: Weak prior keeping an unobservable yaw rate at 0 (rad/s).
    yaw_rate_prior_sigma_radps: float = Field(10.0, gt=0, le=1000)
    #: The radars' Doppler scale: they measure (1 + this) x the true radial velocity, and the
    #: joint fit divides its twist by (1 + this). The odometry's default, -0.003, is what real
    #: ARS408 units read (docs/results.md); 0: take the Doppler as exact.
    speed_scale_error: float = Field(0.0, ge=-0.5, le=0.5)
    seed: int = 0


# --- single sweep ----------------------------------------------------------------------------


def _as_rng(rng) -> np.random.Generator:
    if isinstance(rng, np.random.Generator):
        return rng
    return np.random.default_rng(0 if rng is None else rng)


@functools.lru_cache(maxsize=4096)
def _minimal_sets(seed: int, n: int, k: int, p: int) -> np.ndarray:
    """The joint fit's ``k`` random minimal sets of ``p`` of ``n`` points: a generator seeded
    afresh per frame draws them, so they depend on these four numbers only (kept, read-only:
    seeding a generator cost more than the rest of the draw)."""
    out = np.random.default_rng(seed).integers(0, n, size=(k, p))
    out.flags.writeable = False
    return out


def _ego_rows(ux: np.ndarray, uy: np.ndarray, rot: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(N, 3) rows ``a`` of the fit's model, ``a @ twist`` = minus the radial velocity a static
    point reads: its line of sight (ux, uy) turned into the ego frame by the radar's ``rot``
    ((2, 2), or (N, 2, 2) per point) and u . (w x t) / w for its lever arm ``t``."""
    a = np.empty((len(ux), 3))
    a[:, 0] = ux * rot[..., 0, 0] + uy * rot[..., 0, 1]
    a[:, 1] = ux * rot[..., 1, 0] + uy * rot[..., 1, 1]
    a[:, 2] = a[:, 1] * t[..., 0] - a[:, 0] * t[..., 1]
    return a


def _turned_rows(rows: np.ndarray, levers: np.ndarray) -> np.ndarray:
    """Derivative of the fit's rows (line of sight u, u . (w x t) / w) with respect to the
    radar's mounting yaw: u turns to u + d (-u_y, u_x); ``levers`` is (-t_y, t_x) per row."""
    da = np.empty_like(rows)
    da[:, 0] = -rows[:, 1]
    da[:, 1] = rows[:, 0]
    da[:, 2] = rows[:, 0] * levers[:, 1] - rows[:, 1] * levers[:, 0]
    return da


def _threshold(
    speed: np.ndarray, inlier_threshold_mps: float, relative_threshold: float | None
) -> np.ndarray:
    if relative_threshold is None:
        return np.full_like(speed, inlier_threshold_mps)
    return np.maximum(relative_threshold * speed, inlier_threshold_mps)


def _lstsq_cov(
    a: np.ndarray, b: np.ndarray, noise_floor: float, prior_info: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least squares ``a x = b`` (+ optional zero-mean prior information); (x, cov, residuals)."""
    p = a.shape[1]
    ata = a.T @ a
    if prior_info is not None:
        ata = ata + prior_info
    x = np.linalg.solve(ata, a.T @ b)
    res = b - a @ x
    dof = len(b) - p
    var = float(res @ res) / dof if dof > 0 else 0.0
    var = max(var, noise_floor**2)
    cov = var * np.linalg.inv(ata)
    return x, 0.5 * (cov + cov.T), res


def _invalid_sensor_fit(n: int) -> SensorVelocityFit:
    return SensorVelocityFit(
        velocity_mps=np.zeros(2),
        covariance=np.eye(2) * _HUGE_VARIANCE,
        static_mask=np.zeros(n, dtype=bool),
        ego_static=False,
        num_inliers=0,
        valid=False,
    )


def _observable(a: np.ndarray) -> bool:
    if len(a) < 2:
        return False
    eig = np.linalg.eigvalsh(a.T @ a / len(a))
    return bool(eig[0] > _MIN_DIRECTION_EIGEN)


def fit_sensor_velocity(
    directions: np.ndarray,
    radial_velocity_mps: np.ndarray,
    *,
    inlier_threshold_mps: float = 0.2,
    relative_threshold: float | None = None,
    static_speed_mps: float = 1.0,
    static_fraction: float = 0.5,
    iterations: int = 64,
    min_points: int = 2,
    rng=None,
    static_velocity: Literal["zero", "refit"] = "zero",
    noise_floor_mps: float = 0.05,
    usable: np.ndarray | None = None,
) -> SensorVelocityFit:
    """Fit one radar's velocity over ground (sensor frame) to its points' Doppler.

    ``directions`` (N, 2) are lines of sight (normalised here), ``radial_velocity_mps`` (N,) the raw
    Doppler ``u . (vx, vy)``. ``usable`` (N,) optionally excludes points from the fit (they get
    ``static_mask=False``). Deterministic for a given ``rng`` (Generator or seed; None = seed 0).
    """
    u = np.asarray(directions, dtype=np.float64).reshape(-1, 2)
    vr = np.asarray(radial_velocity_mps, dtype=np.float64).reshape(-1)
    n = len(u)
    if len(vr) != n:
        raise ValueError(f"{n} directions but {len(vr)} radial velocities")
    norm = np.linalg.norm(u, axis=1)
    ok = np.isfinite(vr) & np.isfinite(norm) & (norm > 1e-9)
    if usable is not None:
        ok &= np.asarray(usable, dtype=bool).reshape(-1)
    idx = np.flatnonzero(ok)
    if len(idx) < max(min_points, 1):
        return _invalid_sensor_fit(n)
    a = u[idx] / norm[idx, None]
    b = -vr[idx]  # a @ v_sensor = -v_r for static targets

    # Static-ego rule (AutoPlace DPR).
    slow = np.abs(vr[idx]) < static_speed_mps
    if slow.sum() > static_fraction * len(idx) and slow.sum() >= 1:
        mask = np.zeros(n, dtype=bool)
        mask[idx[slow]] = True
        a_s, b_s = a[slow], b[slow]
        if static_velocity == "refit" and _observable(a_s) and len(a_s) >= min_points:
            v, cov, _ = _lstsq_cov(a_s, b_s, noise_floor_mps)
        else:
            v = np.zeros(2)
            var = max(float(np.mean(b_s**2)), noise_floor_mps**2)
            ata = a_s.T @ a_s
            # A zero velocity is asserted by the rule, not estimated: its precision still follows
            # the geometry, inflated where it cannot observe anything.
            cov = var * np.linalg.inv(ata + np.eye(2) * (var / _HUGE_VARIANCE))
        return SensorVelocityFit(v, cov, mask, True, int(slow.sum()), True)

    if not _observable(a):
        return _invalid_sensor_fit(n)

    # RANSAC over 2-point minimal sets, all hypotheses at once.
    gen = _as_rng(rng)
    m = len(a)
    i = gen.integers(0, m, size=iterations)
    j = gen.integers(0, m - 1, size=iterations)
    j = j + (j >= i)  # distinct pairs
    a1, a2 = a[i], a[j]
    det = a1[:, 0] * a2[:, 1] - a1[:, 1] * a2[:, 0]
    good = np.abs(det) > _MIN_SAMPLE_DET
    best_v = None
    if good.any():
        d = det[good]
        b1, b2 = b[i[good]], b[j[good]]
        # Cramer's rule for [a1; a2] v = [b1; b2].
        vx = (b1 * a2[good, 1] - b2 * a1[good, 1]) / d
        vy = (a1[good, 0] * b2 - a2[good, 0] * b1) / d
        hyp = np.stack([vx, vy], axis=1)  # (K, 2)
        res = np.abs(a @ hyp.T - b[:, None])  # (m, K)
        thr = _threshold(np.linalg.norm(hyp, axis=1), inlier_threshold_mps, relative_threshold)
        counts = (res < thr[None, :]).sum(axis=0)
        best_v = hyp[int(np.argmax(counts))]
    if best_v is None:
        best_v, _, _ = _lstsq_cov(a, b, noise_floor_mps)

    inl = _inliers_2d(a, b, best_v, inlier_threshold_mps, relative_threshold)
    v, cov = best_v, np.eye(2) * _HUGE_VARIANCE
    for _ in range(2):
        if inl.sum() < max(min_points, 2) or not _observable(a[inl]):
            return _invalid_sensor_fit(n)
        v, cov, _ = _lstsq_cov(a[inl], b[inl], noise_floor_mps)
        inl = _inliers_2d(a, b, v, inlier_threshold_mps, relative_threshold)
    mask = np.zeros(n, dtype=bool)
    mask[idx[inl]] = True
    return SensorVelocityFit(v, cov, mask, False, int(inl.sum()), True)


def _inliers_2d(a, b, v, thr_abs, rel) -> np.ndarray:
    thr = _threshold(np.array([np.linalg.norm(v)]), thr_abs, rel)[0]
    return np.abs(a @ v - b) < thr


# --- estimator on sweeps and frames ----------------------------------------------------------


def sweep_doppler(sweep: RadarSweep) -> tuple[np.ndarray, np.ndarray]:
    """(directions (N, 2), raw radial velocity (N,)) of a sweep, from the RAW velocity fields."""
    return sweep.unit_directions, sweep.radial_velocity


class DopplerEstimator:
    """Doppler velocity fits of sweeps (one radar) and frames (all radars jointly)."""

    def __init__(self, config: DopplerConfig | None = None):
        self.config = config or DopplerConfig()

    def _usable(self, sweep: RadarSweep) -> np.ndarray:
        pts = sweep.points
        r = np.hypot(pts["x"].astype(np.float64), pts["y"].astype(np.float64))
        ok = np.isfinite(r) & (r > max(self.config.min_range_m, 1e-6))
        ok &= np.isfinite(pts["vx"]) & np.isfinite(pts["vy"])
        if self.config.require_unambiguous:
            ok &= pts["ambig_state"] == 3
        return ok

    def fit_sweep(self, sweep: RadarSweep) -> SensorVelocityFit:
        c = self.config
        u, vr = sweep_doppler(sweep)
        return fit_sensor_velocity(
            u,
            vr,
            inlier_threshold_mps=c.inlier_threshold_mps,
            relative_threshold=c.relative_threshold,
            static_speed_mps=c.static_speed_mps,
            static_fraction=c.static_fraction,
            iterations=c.iterations,
            min_points=max(2, c.min_points - 1),
            rng=c.seed,
            static_velocity=c.static_velocity,
            noise_floor_mps=c.noise_floor_mps,
            usable=self._usable(sweep),
        )

    def radial_residuals(self, sweep: RadarSweep, fit: EgoMotionFit) -> np.ndarray:
        """(N,) each point's measured radial velocity minus what a static point there would
        read under the frame's fitted twist (m/s, in the radar's own units: the configured
        ``speed_scale_error`` applied back). NaN for a point the fit cannot use (at the sensor,
        non-finite, Doppler-ambiguous where the fit drops those) and for every point of an
        invalid fit. Static points scatter around 0 with the radar's Doppler noise; moving ones
        by their own radial speed."""
        out = np.full(len(sweep), np.nan)
        if not fit.valid or not len(sweep):
            return out
        ok = self._usable(sweep)
        u, vr = sweep_doppler(sweep)
        pose = np.asarray(sweep.ego_from_sensor, dtype=np.float64)
        a = _ego_rows(u[ok, 0], u[ok, 1], pose[:2, :2], pose[:2, 3])
        x = fit.twist_at(sweep.timestamp_us) * (1.0 + (self.config.speed_scale_error or 0.0))
        out[ok] = vr[ok] + a @ x  # the model: a @ x = -v_r of a static point
        return out

    def fit_frame(
        self,
        frame: RadarFrame | Sequence[RadarSweep],
        bounds: TwistBounds | None = None,
        mounting_residuals: bool = False,
        twist_rate: np.ndarray | None = None,
        time_us: int | None = None,
    ) -> EgoMotionFit:
        """All radars of ``frame`` fitted jointly. With ``bounds``, only twists inside them are
        hypotheses: a frame whose radars all see one moving object (a car alongside) can fit it
        better than the static world when few radars report (two side-looking units observe
        each its own velocity, leaving the yaw rate free), and the fit is then a twist no car
        can reach within a frame. A frame with no plausible fit is invalid. With
        ``mounting_residuals`` the fit also reports what its residuals say about each radar's
        mounting yaw (``mounting_information``).

        The radars sweep one after another, tens of ms apart. With ``twist_rate`` (the body
        frame's d(vx, vy, yaw rate)/dt, from the motion so far) each sweep's Doppler is read at
        its own time: its static points see the twist carried from ``time_us`` (default: the
        frame's time) by that rate, and the fit is the twist at ``time_us``. Without it every
        sweep is taken at one time, and a vehicle speeding up or braking reads as turning (the
        left and right units see different speeds)."""
        sweeps: Sequence[RadarSweep]
        if isinstance(frame, RadarFrame):
            sweeps = list(frame.sweeps.values())
            if time_us is None:
                time_us = int(frame.timestamp_us)
        else:
            sweeps = list(frame)
        rate, t_ref = None, 0
        if twist_rate is not None and np.any(twist_rate):
            if time_us is None:
                raise ValueError("fit_frame: a twist_rate needs the frame's time (time_us)")
            rate, t_ref = np.asarray(twist_rate, dtype=np.float64), int(time_us)
        c = self.config
        min_range = max(c.min_range_m, 1e-6)
        channels = tuple(sw.channel for sw in sweeps)
        sizes: dict[str, int] = {sw.channel: len(sw) for sw in sweeps}
        filled = [k for k, sw in enumerate(sweeps) if len(sw)]
        if not filled:
            return self._invalid_frame(sizes, channels, 0)
        # All radars' points in one set of arrays (the fields read once, not through RadarSweep's
        # properties, which rebuild the (N, 2) arrays at every access): same u and v_r as
        # sweep_doppler(), element by element, at one numpy call per field instead of one per
        # field and radar.
        pts = [sweeps[k].points for k in filled]
        px, py, vx, vy = (
            np.concatenate([p[name] for p in pts]).astype(np.float64)
            for name in ("x", "y", "vx", "vy")
        )
        counts_all = np.array([len(p) for p in pts])
        sweep_of = np.repeat(np.arange(len(filled)), counts_all)
        r = np.sqrt(px * px + py * py)
        ok = np.isfinite(r) & (r > min_range) & np.isfinite(vx) & np.isfinite(vy)
        if c.require_unambiguous:
            ok &= np.concatenate([p["ambig_state"] for p in pts]) == 3
        sel = np.flatnonzero(ok)
        if not len(sel):
            return self._invalid_frame(sizes, channels, 0)
        # Radars with a usable point, in frame order: their index is each point's radar_of.
        per_sweep = np.bincount(sweep_of[sel], minlength=len(filled))
        used = np.flatnonzero(per_sweep)
        poses = np.array([np.asarray(sweeps[filled[j]].ego_from_sensor, np.float64) for j in used])
        compact = np.full(len(filled), -1)
        compact[used] = np.arange(len(used))
        radar_of = compact[sweep_of[sel]]
        rot, t = poses[radar_of, :2, :2], poses[radar_of, :2, 3]
        rs = r[sel]
        ux, uy = px[sel] / rs, py[sel] / rs
        a = _ego_rows(ux, uy, rot, t)
        b = -(ux * vx[sel] + uy * vy[sel])
        if rate is not None:
            # a @ (x + dt * rate) = b at each sweep's dt: move the known part to the right
            dt_s = np.array([(sweeps[k].timestamp_us - t_ref) * 1e-6 for k in filled])
            b = b - dt_s[sweep_of[sel]] * (a @ rate) * (1.0 + c.speed_scale_error)
        # Per radar, its lever arm: the relative threshold needs each sensor's speed.
        levers = np.stack([-poses[:, 1, 3], poses[:, 0, 3]], axis=1)
        if bounds is not None and c.speed_scale_error:
            bounds = bounds.scaled(1.0 + c.speed_scale_error)  # in the fit's raw units
        lateral = c.lateral_velocity_sigma_mps
        fallback = c.fallback_lateral_velocity_sigma_mps
        if lateral is None and fallback is not None and not self._observability(a, None)[1]:
            if self._observability(a, fallback, max_yaw_sigma=_FALLBACK_YAW_SIGMA_RADPS)[1]:
                lateral = fallback
        inl, x, cov, ego_static, yaw_obs = self._solve_joint(
            a, b, levers, radar_of, bounds, lateral
        )
        if x is None:
            return self._invalid_frame(sizes, channels, len(a))
        static = np.zeros(len(ok), dtype=bool)
        static[sel] = inl
        masks = {sw.channel: np.zeros(0, dtype=bool) for sw in sweeps}
        for k, mask in zip(filled, np.split(static, np.cumsum(counts_all)[:-1]), strict=True):
            masks[sweeps[k].channel] = mask
        res = a[inl] @ x - b[inl]
        fitted = [sweeps[filled[j]].channel for j in used]
        mount, info, vector = self._mounting(
            a, b, x, inl, radar_of, fitted, levers, lateral, mounting_residuals
        )
        if c.speed_scale_error:
            # Every measured v_r is (1 + e) times the model's, and the model is linear in the
            # twist: the fit (and all that derives from it) is (1 + e) times the true twist.
            gain = 1.0 / (1.0 + c.speed_scale_error)
            x, cov, mount = x * gain, cov * gain**2, mount * gain
        return EgoMotionFit(
            velocity_mps=x[:2].copy(),
            yaw_rate_radps=float(x[2]),
            covariance=cov,
            static_masks=masks,
            ego_static=ego_static,
            num_inliers=int(inl.sum()),
            valid=True,
            num_points=len(a),
            residual_rms_mps=float(np.sqrt(np.mean(res**2))) if len(res) else float("nan"),
            yaw_rate_observable=yaw_obs,
            channels=channels,
            mounting_jacobian=mount,
            mounting_information=info,
            mounting_information_vector=vector,
            time_us=t_ref if rate is not None else None,
            twist_rate=rate if rate is not None else np.zeros(3),
        )

    def _mounting(self, a, b, x, inl, radar_of, channels, levers, lateral, residuals: bool):
        """What the fit says of each radar's mounting yaw, the inliers' rows and residuals
        shared: the twist's (3, 5) Jacobian and, with ``residuals``, the yaws' (5, 5)
        information and (5,) vector (else zeros), columns in RADAR_CHANNELS order.

        Turning radar i by d turns its lines of sight u to u + d (-u_y, u_x), which changes its
        rows of the linear system by d da_p. The least-squares twist then moves by
        (A^T A)^-1 sum_p (da_p r_p - a_p (da_p . x)) over its inliers p (the Jacobian). Each
        point's predicted radial velocity moves by d (da_p . x), so the residuals r = b - A x
        regress on the columns D (one per radar) next to A, and the Schur complement of A's
        block gives the yaws' information D^T D - D^T A (A^T A)^-1 A^T D and vector
        D^T r - D^T A (A^T A)^-1 A^T r, in units of the residual variance."""
        n_ch = len(RADAR_CHANNELS)
        jac, info, vector = np.zeros((3, n_ch)), np.zeros((n_ch, n_ch)), np.zeros(n_ch)
        if not inl.any() or not np.any(x):
            return jac, info, vector
        ai, ri = a[inl], radar_of[inl]
        r = b[inl] - ai @ x
        da = _turned_rows(ai, levers[ri])
        d = da @ x
        ata = ai.T @ ai
        # per-radar sums over its points (bincount: one pass, no mask per radar)
        cols = np.array([RADAR_CHANNELS.index(ch) for ch in channels])[ri]
        terms = da * r[:, None] - ai * d[:, None]
        m = inv3(ata + self._prior(lateral) * self.config.noise_floor_mps**2)
        jac = m @ np.stack(
            [np.bincount(cols, weights=terms[:, j], minlength=n_ch) for j in range(3)]
        )
        if residuals:
            var = max(float(r @ r) / max(len(r) - 3, 1), self.config.noise_floor_mps**2)
            dtd = np.bincount(cols, weights=d * d, minlength=n_ch)
            dtr = np.bincount(cols, weights=d * r, minlength=n_ch)
            dta = np.stack(
                [np.bincount(cols, weights=d * ai[:, j], minlength=n_ch) for j in range(3)], axis=1
            )
            m = inv3(ata + self._prior(lateral) * var)
            info = (np.diag(dtd) - dta @ m @ dta.T) / var
            info = 0.5 * (info + info.T)
            vector = (dtr - dta @ m @ (ai.T @ r)) / var
        return jac, info, vector

    def _invalid_frame(
        self, sizes: Mapping[str, int], channels: tuple[str, ...], num_points: int
    ) -> EgoMotionFit:
        return EgoMotionFit(
            velocity_mps=np.zeros(2),
            yaw_rate_radps=0.0,
            covariance=np.eye(3) * _HUGE_VARIANCE,
            static_masks={ch: np.zeros(n, dtype=bool) for ch, n in sizes.items()},
            ego_static=False,
            num_inliers=0,
            valid=False,
            num_points=num_points,
            yaw_rate_observable=False,
            channels=channels,
        )

    def _prior(self, lateral: float | None) -> np.ndarray:
        """Prior information: the weak zero yaw rate, and ``lateral`` (m/s) on the lateral
        velocity unless None."""
        c = self.config
        info = np.zeros((3, 3))
        info[2, 2] = 1.0 / c.yaw_rate_prior_sigma_radps**2
        if lateral is not None:
            info[1, 1] = 1.0 / lateral**2
        return info

    def _solve(
        self, a: np.ndarray, b: np.ndarray, lateral: float | None, ata: np.ndarray | None = None
    ):
        """Least squares with the priors scaled to the residual variance (information form).
        ``ata`` = ``a.T @ a`` when the caller has it already."""
        c = self.config
        prior = self._prior(lateral)
        if ata is None:
            ata = a.T @ a
        atb = a.T @ b
        # First pass fixes the residual variance, which the priors (given in physical sigmas) must
        # be expressed against, since the covariance is that variance times (A^T A + P)^-1.
        x = solve3(ata + prior * c.noise_floor_mps**2, atb)
        res = b - a @ x
        dof = len(b) - 3
        var = max(float(res @ res) / dof if dof > 0 else 0.0, c.noise_floor_mps**2)
        inv = inv3(ata + prior * var)
        x = inv @ atb
        cov = var * inv
        return x, 0.5 * (cov + cov.T)

    def _observability(
        self,
        a: np.ndarray,
        lateral: float | None,
        ata: np.ndarray | None = None,
        max_yaw_sigma: float = _YAW_OBSERVABLE_SIGMA_RADPS,
    ) -> tuple[bool, bool]:
        """(velocity observable, yaw rate observable to ``max_yaw_sigma``) from the geometry and
        the lateral prior ``lateral`` (None: the geometry alone).
        ``ata`` = ``a.T @ a`` when the caller has it already. 2x2 algebra in closed form: this
        runs several times per frame and np.linalg's per-call overhead dominated it."""
        n = len(a)
        if n < 2:
            return False, False
        if ata is None:
            ata = a.T @ a
        # Smallest eigenvalue of the direction block A_v^T A_v / n (as _observable()).
        p, q, r = ata[0, 0] / n, ata[0, 1] / n, ata[1, 1] / n
        smallest = 0.5 * (p + r) - np.hypot(0.5 * (p - r), q)
        if not smallest > _MIN_DIRECTION_EIGEN:
            return False, False
        c = self.config
        # Information of the data at the noise floor plus the lateral prior (not the weak yaw
        # prior, which exists only to keep an unobservable yaw rate finite).
        info = ata / c.noise_floor_mps**2
        i00, i01, i11 = info[0, 0], info[0, 1], info[1, 1]
        if lateral is not None:
            i11 = i11 + 1.0 / lateral**2
        # Yaw-rate information left once (vx, vy) are estimated (Schur complement).
        g0, g1 = info[0, 2], info[1, 2]
        det = i00 * i11 - i01 * i01
        schur = info[2, 2] - (g0 * (i11 * g0 - i01 * g1) + g1 * (i00 * g1 - i01 * g0)) / det
        return True, bool(schur > 1.0 / max_yaw_sigma**2)

    def _solve_joint(
        self,
        a: np.ndarray,
        b: np.ndarray,
        levers: np.ndarray,
        radar_of: np.ndarray,
        bounds: TwistBounds | None,
        lateral: float | None,
    ):
        """(inliers, twist, covariance, ego static, yaw rate observable); Nones when no fit."""
        c = self.config
        n = len(a)
        none = (None, None, None, False, False)
        if n < c.min_points:
            return none
        slow = np.abs(b) < c.static_speed_mps
        ego_static = bool(slow.sum() > c.static_fraction * n)
        # A vehicle that cannot have stopped by now is not declared static.
        zero_ok = bounds is None or bool(bounds.contains(np.zeros(3)))
        if ego_static and c.static_velocity == "zero":
            return self._static_zero(a, b, slow, lateral) if zero_ok else none
        # "refit" estimates the velocity as when moving: fitting only the points slower than
        # static_speed_mps would truncate on the measurement itself and bias a creeping car's
        # speed low (real nuScenes, braking below 1.3 m/s: 0.1-0.2 m/s too slow).
        fit = self._solve_moving(a, b, levers, radar_of, bounds, lateral)
        if fit is None:
            return self._static_zero(a, b, slow, lateral) if ego_static and zero_ok else none
        inl, x, cov, yaw_ok = fit
        return inl, x, cov, ego_static, yaw_ok

    def _static_zero(self, a: np.ndarray, b: np.ndarray, slow: np.ndarray, lateral: float | None):
        """The static-ego rule's zero twist; its precision follows the slow points' geometry."""
        c = self.config
        a_s, b_s = a[slow], b[slow]
        ata_s = a_s.T @ a_s
        yaw_ok = self._observability(a_s, lateral, ata_s)[1]
        var = max(float(np.mean(b_s**2)), c.noise_floor_mps**2)
        ata = ata_s + self._prior(lateral) * var + np.eye(3) * (var / _HUGE_VARIANCE)
        cov = var * inv3(ata)
        return slow, np.zeros(3), 0.5 * (cov + cov.T), True, yaw_ok

    def _solve_moving(
        self,
        a: np.ndarray,
        b: np.ndarray,
        levers: np.ndarray,
        radar_of: np.ndarray,
        bounds: TwistBounds | None,
        lateral: float | None,
    ):
        """RANSAC over minimal sets (those inside ``bounds``), then least squares on the
        consensus set (twice); (inliers, twist, covariance, yaw rate observable) or None."""
        c = self.config
        n = len(a)
        vel_ok, yaw_geometric = self._observability(a, None)
        if not vel_ok:
            return None

        def inliers(x: np.ndarray) -> np.ndarray:
            # Per point, the sensor speed |v + w x t_i| sets the relative threshold.
            if c.relative_threshold is None:
                return np.abs(a @ x - b) < c.inlier_threshold_mps
            speed = np.linalg.norm(x[:2] + x[2] * levers, axis=1)[radar_of]
            thr = _threshold(speed, c.inlier_threshold_mps, c.relative_threshold)
            return np.abs(a @ x - b) < thr

        k = c.iterations
        # 3-point minimal sets where the radars' geometry observes the yaw rate; else 2 points,
        # for (vx, yaw rate) with the lateral prior's vy = 0, or for (vx, vy) with the yaw rate 0.
        if yaw_geometric:
            cols = [0, 1, 2]
        else:
            cols = [0, 2] if lateral is not None else [0, 1]
        p = len(cols)
        if n < p:
            return None
        # Duplicate indices give a singular minimal set, which the determinant test drops.
        samples = _minimal_sets(c.seed, n, k, p)
        best_x, best_count = None, -1
        am = a[samples][:, :, cols]  # (k, p, p)
        bm = b[samples]
        dets = np.linalg.det(am)
        good = np.abs(dets) > _MIN_SAMPLE_DET * (1.0 if p == 2 else 0.5)
        if good.any():
            hyp = np.zeros((int(good.sum()), 3))
            hyp[:, cols] = np.linalg.solve(am[good], bm[good][..., None])[..., 0]
        else:
            hyp = np.zeros((0, 3))
        if bounds is not None:
            # Where no random minimal set lies inside the bounds (few static points), the
            # bounds' centre, the vehicle's last twist, is the hypothesis.
            hyp = hyp[bounds.contains(hyp)]
            if not len(hyp):
                hyp = bounds.center[None, :]
        if len(hyp):
            res = np.abs(a @ hyp.T - b[:, None])  # (n, K)
            if c.relative_threshold is None:
                counts = (res < c.inlier_threshold_mps).sum(axis=0)
            else:
                # Speed of each radar under each hypothesis, (radars, K), then per point.
                speed = np.linalg.norm(
                    hyp[None, :, :2] + hyp[None, :, 2:3] * levers[:, None, :], axis=2
                )
                thr = _threshold(speed, c.inlier_threshold_mps, c.relative_threshold)[radar_of]
                counts = (res < thr).sum(axis=0)
            best = int(np.argmax(counts))
            best_x, best_count = hyp[best], counts[best]
        if best_x is None or best_count < p:
            best_x, _ = self._solve(a, b, lateral)
        inl = inliers(best_x)
        x, cov = best_x, np.eye(3) * _HUGE_VARIANCE
        for _ in range(2):
            if inl.sum() < c.min_points:
                return None
            a_i = a[inl]
            ata_i = a_i.T @ a_i
            if not self._observability(a_i, lateral, ata_i)[0]:
                return None
            x, cov = self._solve(a_i, b[inl], lateral, ata_i)
            inl = inliers(x)
        if bounds is not None and not bounds.contains(x):
            return None
        yaw_ok = self._observability(a[inl], lateral)[1]
        return inl, x, cov, yaw_ok
