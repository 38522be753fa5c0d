"""Synthetic radar sweeps with the real nuScenes semantics, built directly in memory.

Raw velocity ``(vx, vy)`` is the target's velocity relative to the sensor (not purely radial: a
random tangential part is added, as on real files); ``(vx_comp, vy_comp)`` is purely radial and
satisfies ``u . (v - v_comp) = -u . v_sensor`` exactly, the oracle of the format notes. Positions
carry azimuth and range noise, so the line of sight used for the fit is the *measured* one.
"""

from __future__ import annotations

import numpy as np

from radarslam.geometry import invert, make_transform, se2_to_matrix
from radarslam.types import RADAR_CHANNELS, RADAR_DTYPE, RadarFrame, RadarSweep


def yaw_quat(yaw_rad: float) -> list[float]:
    return [np.cos(yaw_rad / 2), 0.0, 0.0, np.sin(yaw_rad / 2)]


#: Mountings close to nuScenes' calibrated_sensor (x forward, y left, yaw of the boresight).
MOUNTS: dict[str, np.ndarray] = {
    "RADAR_FRONT": make_transform([3.41, 0.0, 0.5], yaw_quat(0.0)),
    "RADAR_FRONT_LEFT": make_transform([2.42, 0.80, 0.5], yaw_quat(np.deg2rad(90))),
    "RADAR_FRONT_RIGHT": make_transform([2.42, -0.80, 0.5], yaw_quat(np.deg2rad(-90))),
    "RADAR_BACK_LEFT": make_transform([-0.56, 0.62, 0.5], yaw_quat(np.deg2rad(178))),
    "RADAR_BACK_RIGHT": make_transform([-0.56, -0.62, 0.5], yaw_quat(np.deg2rad(-178))),
}
assert set(MOUNTS) == set(RADAR_CHANNELS)


def sensor_velocity(ego_from_sensor: np.ndarray, v_ego: np.ndarray, yaw_rate: float) -> np.ndarray:
    """Sensor velocity over ground in the sensor frame: R^T (v + w x t)."""
    r = ego_from_sensor[:2, :2]
    t = ego_from_sensor[:2, 3]
    return r.T @ (np.asarray(v_ego, dtype=float) + yaw_rate * np.array([-t[1], t[0]]))


def make_points(
    rng: np.random.Generator,
    xy_true: np.ndarray,
    v_sensor: np.ndarray,
    target_velocity_sensor: np.ndarray,
    *,
    sigma_vr_mps: float = 0.15,
    sigma_azimuth_rad: float = np.deg2rad(0.5),
    sigma_range_m: float = 0.2,
    tangential_mps: float = 2.0,
    doppler_scale_error: float = 0.0,
) -> np.ndarray:
    """Radar records of targets at ``xy_true`` (sensor frame) moving with the given velocities;
    the radar reads (1 + ``doppler_scale_error``) x the true radial velocity."""
    n = len(xy_true)
    rng_true = np.linalg.norm(xy_true, axis=1)
    az_true = np.arctan2(xy_true[:, 1], xy_true[:, 0])
    u_true = xy_true / rng_true[:, None]
    v_rel = target_velocity_sensor - v_sensor[None, :]
    vr = (1.0 + doppler_scale_error) * np.einsum("ij,ij->i", u_true, v_rel)
    vr = vr + rng.normal(0, sigma_vr_mps, n)
    az = az_true + rng.normal(0, sigma_azimuth_rad, n)
    rr = rng_true + rng.normal(0, sigma_range_m, n)
    u = np.column_stack([np.cos(az), np.sin(az)])
    perp = np.column_stack([-u[:, 1], u[:, 0]])
    v_raw = vr[:, None] * u + rng.normal(0, tangential_mps, n)[:, None] * perp
    v_comp = (np.einsum("ij,ij->i", u, v_raw) + u @ v_sensor)[:, None] * u
    pts = np.zeros(n, dtype=RADAR_DTYPE)
    pts["x"], pts["y"] = rr * u[:, 0], rr * u[:, 1]
    pts["vx"], pts["vy"] = v_raw[:, 0], v_raw[:, 1]
    pts["vx_comp"], pts["vy_comp"] = v_comp[:, 0], v_comp[:, 1]
    pts["dyn_prop"] = 1
    pts["ambig_state"] = 3
    pts["rcs"] = rng.normal(5, 5, n)
    pts["id"] = np.arange(n)
    return pts


def random_sweep_points(
    rng: np.random.Generator,
    v_sensor: np.ndarray,
    *,
    n: int = 60,
    moving_fraction: float = 0.3,
    fov_deg: float = 60.0,
    **noise,
) -> tuple[np.ndarray, np.ndarray]:
    """(points, is_moving) for ``n`` targets in the field of view, a fraction of them moving."""
    az = rng.uniform(-np.deg2rad(fov_deg), np.deg2rad(fov_deg), n)
    r = rng.uniform(5, 80, n)
    xy = np.column_stack([r * np.cos(az), r * np.sin(az)])
    moving = rng.random(n) < moving_fraction
    vt = np.zeros((n, 2))
    vt[moving] = rng.normal(0, 8, (int(moving.sum()), 2))
    return make_points(rng, xy, v_sensor, vt, **noise), moving


def oracle_sensor_velocity(points: np.ndarray) -> np.ndarray:
    """The exact sensor velocity from u . (v - v_comp) = -u . v_sensor (least squares)."""
    xy = np.column_stack([points["x"], points["y"]]).astype(float)
    u = xy / np.linalg.norm(xy, axis=1, keepdims=True)
    d = np.column_stack(
        [points["vx"] - points["vx_comp"], points["vy"] - points["vy_comp"]]
    ).astype(float)
    return np.linalg.lstsq(u, -np.einsum("ij,ij->i", u, d), rcond=None)[0]


def make_sweep(
    channel: str,
    points: np.ndarray,
    *,
    timestamp_us: int = 0,
    world_from_ego: np.ndarray | None = None,
) -> RadarSweep:
    return RadarSweep(
        channel=channel,
        timestamp_us=timestamp_us,
        points=points,
        ego_from_sensor=MOUNTS[channel],
        world_from_ego=np.eye(4) if world_from_ego is None else world_from_ego,
    )


def make_frame(
    rng: np.random.Generator,
    v_ego: np.ndarray,
    yaw_rate: float,
    *,
    channels=RADAR_CHANNELS,
    n: int = 60,
    moving_fraction: float = 0.3,
    timestamp_us: int = 0,
    **noise,
) -> RadarFrame:
    """A frame of random targets (no world map: for Doppler-only tests)."""
    sweeps = {}
    for ch in channels:
        vs = sensor_velocity(MOUNTS[ch], v_ego, yaw_rate)
        pts, _ = random_sweep_points(rng, vs, n=n, moving_fraction=moving_fraction, **noise)
        sweeps[ch] = make_sweep(ch, pts, timestamp_us=timestamp_us)
    return RadarFrame(timestamp_us=timestamp_us, sweeps=sweeps, world_from_ego=np.eye(4))


# --- a small static world driven through: for registration / odometry tests -------------------


class World:
    """Static reflectors (walls as point rows, poles) plus optional moving cars."""

    def __init__(self, rng: np.random.Generator, *, extent_m: float = 400.0, n_static: int = 3000):
        pts = []
        # Building fronts along both sides of a grid of streets: rows of reflectors.
        for _ in range(n_static // 20):
            c = rng.uniform(-extent_m, extent_m, 2)
            ang = rng.uniform(0, np.pi)
            d = np.array([np.cos(ang), np.sin(ang)])
            s = np.linspace(-15, 15, 20)
            pts.append(c + s[:, None] * d + rng.normal(0, 0.05, (20, 2)))
        self.static_xy = np.concatenate(pts)

    def observe(
        self,
        rng: np.random.Generator,
        channel: str,
        world_from_ego: np.ndarray,
        v_ego: np.ndarray,
        yaw_rate: float,
        *,
        max_points: int = 125,
        max_range_m: float = 100.0,
        fov_deg: float = 60.0,
        moving_fraction: float = 0.0,
        **noise,
    ) -> np.ndarray:
        """One sweep of ``channel`` from the pose: visible static points (+ moving clutter)."""
        world_from_sensor = world_from_ego @ MOUNTS[channel]
        sensor_from_world = invert(world_from_sensor)
        xy = self.static_xy @ sensor_from_world[:2, :2].T + sensor_from_world[:2, 3]
        r = np.linalg.norm(xy, axis=1)
        az = np.arctan2(xy[:, 1], xy[:, 0])
        vis = (r > 1.0) & (r < max_range_m) & (np.abs(az) < np.deg2rad(fov_deg))
        xy = xy[vis]
        if len(xy) > max_points:
            xy = xy[rng.choice(len(xy), max_points, replace=False)]
        vs = sensor_velocity(MOUNTS[channel], v_ego, yaw_rate)
        vt = np.zeros_like(xy)
        n_mov = round(moving_fraction * len(xy) / max(1e-9, 1 - moving_fraction))
        if n_mov:
            az_m = rng.uniform(-np.deg2rad(fov_deg), np.deg2rad(fov_deg), n_mov)
            r_m = rng.uniform(5, 60, n_mov)
            xy = np.concatenate([xy, np.column_stack([r_m * np.cos(az_m), r_m * np.sin(az_m)])])
            # Other cars: roughly along the ego's heading, in the sensor frame.
            heading = MOUNTS[channel][:2, :2].T @ np.array([1.0, 0.0])
            speed = rng.uniform(3, 15, n_mov) * rng.choice([-1, 1], n_mov)
            vt = np.concatenate([vt, speed[:, None] * heading[None, :]])
        if len(xy) == 0:
            return np.zeros(0, dtype=RADAR_DTYPE)
        return make_points(rng, xy, vs, vt, **noise)


def drive(
    world: World,
    rng: np.random.Generator,
    *,
    num_frames: int,
    dt_s: float = 1 / 13,
    speed_mps=10.0,
    yaw_rate_radps=0.0,
    stagger_s: float = 0.015,
    missing: dict[str, tuple[int, int]] | None = None,
    empty: tuple[int, int] | None = None,
    moving_fraction: float = 0.0,
    key_frame_every: int = 6,
    **noise,
) -> list[RadarFrame]:
    """Frames along a unicycle path; radars fire staggered within the frame (up to ~60 ms). The
    radars read Doppler as the odometry's default calibration expects real ones to
    (``doppler.speed_scale_error``) unless ``noise`` says otherwise."""
    from radarslam.odometry.config import OdometryConfig

    noise.setdefault("doppler_scale_error", OdometryConfig().doppler.speed_scale_error)
    frames = []
    x = y = yaw = 0.0
    t0 = 1_600_000_000_000_000
    missing = missing or {}

    def profile(value, k):
        return value(k * dt_s) if callable(value) else value

    for k in range(num_frames):
        sweeps = {}
        t_ref = t0 + round(k * dt_s * 1e6)
        world_from_ego_ref = se2_to_matrix(x, y, yaw)
        for ci, ch in enumerate(RADAR_CHANNELS):
            lo_hi = missing.get(ch)
            if lo_hi and lo_hi[0] <= k < lo_hi[1]:
                continue
            # Each radar fires at its own offset; integrate the unicycle to that time.
            dt_c = ci * stagger_s
            v, w = profile(speed_mps, k), profile(yaw_rate_radps, k)
            xc, yc, yawc = _integrate(x, y, yaw, v, w, dt_c)
            wfe = se2_to_matrix(xc, yc, yawc)
            if empty and empty[0] <= k < empty[1]:
                pts = np.zeros(0, dtype=RADAR_DTYPE)
            else:
                pts = world.observe(
                    rng, ch, wfe, np.array([v, 0.0]), w, moving_fraction=moving_fraction, **noise
                )
            sweeps[ch] = make_sweep(
                ch, pts, timestamp_us=t_ref + round(dt_c * 1e6), world_from_ego=wfe
            )
        frames.append(
            RadarFrame(
                timestamp_us=t_ref,
                sweeps=sweeps,
                world_from_ego=world_from_ego_ref,
                scene_name="synthetic",
                is_key_frame=k % key_frame_every == 0,
                sample_token=f"sample{k}" if k % key_frame_every == 0 else "",
            )
        )
        v, w = profile(speed_mps, k), profile(yaw_rate_radps, k)
        x, y, yaw = _integrate(x, y, yaw, v, w, dt_s)
    return frames


def _integrate(x, y, yaw, v, w, dt):
    if abs(w) < 1e-9:
        return x + v * dt * np.cos(yaw), y + v * dt * np.sin(yaw), yaw
    yaw2 = yaw + w * dt
    return (
        x + v / w * (np.sin(yaw2) - np.sin(yaw)),
        y - v / w * (np.cos(yaw2) - np.cos(yaw)),
        yaw2,
    )
