"""ARS408-like radar model: 2-D visibility, detection probability, noise, ghosts, clutter, fields.

One call of :meth:`RadarModel.sweep` turns the world at one instant into one sweep of at most 125
clusters in the sensor frame with all 18 nuScenes fields. The velocity fields follow the real
semantics: ``v_comp`` is purely radial, the raw ``v`` is not, and
``u . (v - v_comp) = -u . v_sensor``
holds exactly for the sensor velocity of the sweep (float32 rounding aside).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from radarslam.geometry import make_transform, rot2
from radarslam.sim.config import RadarConfig
from radarslam.sim.world import (
    CLUTTER,
    CYCLIST,
    GHOST,
    MOVING_CAR,
    PARKED_CAR,
    PEDESTRIAN,
    Boxes,
    Scatterers,
)
from radarslam.types import RADAR_DTYPE


@dataclass(frozen=True)
class RadarMount:
    channel: str
    x_m: float
    y_m: float
    z_m: float
    yaw_deg: float
    roll_deg: float = 0.0
    pitch_deg: float = 0.0

    def ego_from_sensor(self) -> np.ndarray:
        r, p, y = np.deg2rad([self.roll_deg, self.pitch_deg, self.yaw_deg])
        # Extrinsic x-y-z (roll, pitch, yaw) = R_z(yaw) R_y(pitch) R_x(roll), as a quaternion.
        cr, sr = np.cos(r / 2), np.sin(r / 2)
        cp, sp = np.cos(p / 2), np.sin(p / 2)
        cy, sy = np.cos(y / 2), np.sin(y / 2)
        q = [
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ]
        return make_transform([self.x_m, self.y_m, self.z_m], q)


#: Mounting poses close to the nuScenes calibration (ego frame = rear axle).
NUSCENES_MOUNTS: tuple[RadarMount, ...] = (
    RadarMount("RADAR_FRONT", 3.412, 0.0, 0.50, 0.0, 0.0, 0.0),
    RadarMount("RADAR_FRONT_LEFT", 2.422, 0.800, 0.78, 88.3, 0.0, 0.0),
    RadarMount("RADAR_FRONT_RIGHT", 2.422, -0.800, 0.77, -88.9, 0.0, 0.0),
    RadarMount("RADAR_BACK_LEFT", -0.562, 0.628, 0.53, 174.2, 0.0, 0.0),
    RadarMount("RADAR_BACK_RIGHT", -0.562, -0.618, 0.53, -176.2, 0.0, 0.0),
)


@dataclass(frozen=True)
class MountingError:
    """How one simulated unit differs from its written (nominal) calibration."""

    yaw_deg: float  # true mounting yaw minus the nominal one
    timestamp_offset_s: float  # written timestamp minus the true measurement time


def mounting_errors(cfg: RadarConfig, seed: int) -> dict[str, MountingError]:
    """Per-channel errors of one simulated vehicle (the same in every log of a dataroot)."""
    rng = np.random.default_rng([seed, 808])
    n = len(NUSCENES_MOUNTS)
    yaw = rng.normal(0.0, cfg.mounting_yaw_std_deg, n)
    dt = rng.normal(0.0, cfg.timestamp_offset_std_s, n)
    knocked = rng.uniform(0.0, 1.0, n) < cfg.mounting_yaw_outlier_probability
    yaw = np.where(knocked, rng.normal(0.0, cfg.mounting_yaw_outlier_std_deg, n), yaw)
    given = cfg.mounting_yaw_error_deg or {}
    return {
        m.channel: MountingError(float(given.get(m.channel, yaw[i])), float(dt[i]))
        for i, m in enumerate(NUSCENES_MOUNTS)
    }


def clock_offset_s(cfg: RadarConfig, seed: int, log_index: int) -> float:
    """One log's written radar timestamps minus the true measurement times (ego-pose clock)."""
    rng = np.random.default_rng([seed, 809, log_index])
    return float(cfg.clock_offset_mean_s + rng.normal(0.0, cfg.clock_offset_std_s))


#: Per-point ground truth written to the sidecar: object class (``world.CLASS_NAMES``), candidate
#: kind (real, weak, mirror ghost, double bounce, static clutter, random clutter) and the true
#: speed over ground of what produced the point (apparent for ghosts).
LABEL_DTYPE = np.dtype([("cls", "i1"), ("kind", "i1"), ("ground_speed_mps", "<f4")])

# Candidate kinds (decide the quality fields).
REAL, WEAK, MIRROR, DOUBLE, CLUTTER_STATIC, CLUTTER_RANDOM, SIDELOBE = 0, 1, 2, 3, 4, 5, 6
_SELECT_WEIGHT = np.array([4.0, 1.5, 1.5, 1.0, 1.0, 1.0, 1.0])
# (p of invalid_state 0, other states, their weights) per kind.
_INVALID = {
    REAL: (0.85, [16, 9, 11, 8, 17], [4, 2, 2, 1, 1]),
    WEAK: (0.45, [4, 1, 11, 16, 9], [4, 2, 2, 2, 1]),
    MIRROR: (0.40, [6, 16, 11], [5, 1, 1]),
    DOUBLE: (0.30, [14, 6, 12], [2, 2, 1]),
    CLUTTER_STATIC: (0.15, [4, 1, 11, 9, 16, 3, 15], [5, 3, 3, 2, 3, 1, 1]),
    CLUTTER_RANDOM: (0.2, [1, 4, 11, 16, 12, 14], [3, 3, 2, 2, 1, 1]),
    SIDELOBE: (0.45, [11, 16, 9, 4, 17], [3, 3, 2, 2, 1]),
}
_INV_P0 = np.array([_INVALID[k][0] for k in range(7)])
_INV_STATES = np.zeros((7, 7), np.int64)
_INV_CUM = np.ones((7, 7))
for _k, (_p0, _states, _w) in _INVALID.items():
    _INV_STATES[_k, : len(_states)] = _states
    _INV_STATES[_k, len(_states) :] = _states[-1]
    _INV_CUM[_k, : len(_w)] = np.cumsum(_w) / np.sum(_w)
_PDH0_BASE = np.array([1, 2, 2, 3, 3, 4, 2])
_AMBIG3 = np.array([0.97, 0.93, 0.85, 0.8, 0.84, 0.7, 0.9])
_RMS_RATIO = np.log(1.2884)

# Car scatterers in the box frame, per unit (half length, half width): position, normal, lobe,
# specular gain, diffuse rcs mean.
_CAR_PTS = np.array(
    [  # x, y, nx, ny, lobe_deg, spec_db, rcs_db
        [1, 1, 1, 1, 50, 4, 10],
        [1, -1, 1, -1, 50, 4, 10],
        [-1, 1, -1, 1, 50, 4, 10],
        [-1, -1, -1, -1, 50, 4, 10],
        [0, 1, 0, 1, 18, 9, 5],
        [0, -1, 0, -1, 18, 9, 5],
        [1, 0, 1, 0, 25, 6, 7],
        [-1, 0, -1, 0, 25, 6, 8],
        [0.55, 1, 0, 1, 70, 0, 4],
        [0.55, -1, 0, -1, 70, 0, 4],
        [-0.55, 1, 0, 1, 70, 0, 4],
        [-0.55, -1, 0, -1, 70, 0, 4],
    ]
)


def rms_code(sigma: np.ndarray) -> np.ndarray:
    """ARS408 rms enumeration: code k means sigma < 0.005 * 1.2884**k (31 = invalid)."""
    k = np.ceil(np.log(np.maximum(sigma, 1e-6) / 0.005) / _RMS_RATIO)
    return np.clip(k, 0, 30).astype(np.int8)


def box_scatterers(boxes: Boxes, rng: np.random.Generator):
    """Scatterers of cars/cyclists/pedestrians plus their velocity, stopped flag, occluders."""
    if len(boxes) == 0:
        return Scatterers.empty(), np.zeros((0, 2)), np.zeros(0, bool), np.zeros((0, 4))
    car = (boxes.cls == MOVING_CAR) | (boxes.cls == PARKED_CAR)
    parts, vel, stop = [], [], []
    c, s = np.cos(boxes.yaw), np.sin(boxes.yaw)
    if car.any():
        idx = np.flatnonzero(car)
        k = len(_CAR_PTS)
        hl, hw = 0.5 * boxes.length[idx], 0.5 * boxes.width[idx]
        lx = (_CAR_PTS[None, :, 0] * hl[:, None]).ravel()
        ly = (_CAR_PTS[None, :, 1] * hw[:, None]).ravel()
        nx = np.tile(_CAR_PTS[:, 2], len(idx))
        ny = np.tile(_CAR_PTS[:, 3], len(idx))
        nn = np.hypot(nx, ny)
        nx, ny = nx / nn, ny / nn
        cc, ss = np.repeat(c[idx], k), np.repeat(s[idx], k)
        xy = np.repeat(boxes.xy[idx], k, axis=0) + np.column_stack(
            [cc * lx - ss * ly, ss * lx + cc * ly]
        )
        normal = np.column_stack([cc * nx - ss * ny, ss * nx + cc * ny])
        m = len(xy)
        parts.append(
            Scatterers(
                xy,
                np.tile(_CAR_PTS[:, 6], len(idx)) + 2.0 + rng.normal(0, 3.0, m),
                np.repeat(boxes.cls[idx], k),
                normal,
                np.deg2rad(np.tile(_CAR_PTS[:, 4], len(idx))),
                np.tile(_CAR_PTS[:, 5], len(idx)),
                np.full(m, 0.9),
                np.full(m, 0.05),
            )
        )
        vel.append(np.repeat(boxes.velocity[idx], k, axis=0))
        stop.append(np.repeat(boxes.stopped[idx], k))
    for cls, rcs, n_pts, jit in ((CYCLIST, -1.0, 2, 0.3), (PEDESTRIAN, -3.0, 1, 0.2)):
        idx = np.flatnonzero(boxes.cls == cls)
        if len(idx) == 0:
            continue
        xy = np.repeat(boxes.xy[idx], n_pts, axis=0)
        m = len(xy)
        parts.append(
            Scatterers(
                xy,
                rcs + rng.normal(0, 2.0, m),
                np.full(m, cls, np.int8),
                np.zeros((m, 2)),
                np.ones(m),
                np.zeros(m),
                np.full(m, 0.7),
                np.full(m, jit),
            )
        )
        v = np.repeat(boxes.velocity[idx], n_pts, axis=0)
        if cls == PEDESTRIAN:  # swinging limbs: micro-Doppler
            v = v + rng.normal(0, 0.4, v.shape) * (np.linalg.norm(v, axis=1, keepdims=True) > 0.1)
        vel.append(v)
        stop.append(np.repeat(boxes.stopped[idx], n_pts))
    # A car's two diagonals block exactly its silhouette, at or behind its visible faces.
    idx = np.flatnonzero(car)
    hl, hw = 0.5 * boxes.length[idx], 0.5 * boxes.width[idx]
    ci, si = c[idx], s[idx]
    cx, cy = boxes.xy[idx, 0], boxes.xy[idx, 1]
    p1 = np.column_stack([cx + ci * hl - si * hw, cy + si * hl + ci * hw])
    p2 = np.column_stack([cx - ci * hl + si * hw, cy - si * hl - ci * hw])
    p3 = np.column_stack([cx + ci * hl + si * hw, cy + si * hl - ci * hw])
    p4 = np.column_stack([cx - ci * hl - si * hw, cy - si * hl + ci * hw])
    occ = np.vstack([np.hstack([p1, p2]), np.hstack([p3, p4])])
    return (Scatterers.concat(parts), np.concatenate(vel), np.concatenate(stop), occ)


@dataclass
class SweepWorld:
    """What one sweep sees: static scatterers and segments near the sensor, plus boxes now."""

    static: Scatterers
    occluders: np.ndarray  # (M, 4) world
    reflectors: np.ndarray  # (R, 4) world
    boxes: Boxes


class RadarModel:
    """One unit: the shared radar configuration plus its channel's sensitivity and clutter."""

    def __init__(self, cfg: RadarConfig, channel: str | None = None):
        self.cfg = cfg
        self.gain_db = float(cfg.channel_gain_db.get(channel, 0.0)) if channel else 0.0
        self.clutter_scale = float(cfg.channel_clutter_scale.get(channel, 1.0)) if channel else 1.0
        self.near_rolloff_db = float(
            cfg.channel_near_rolloff_db.get(channel, cfg.near_rolloff_db)
            if channel
            else cfg.near_rolloff_db
        )
        self.bin_w = np.deg2rad(0.25)
        self.lim = np.deg2rad(cfg.near_fov_deg + 1.0)
        self.n_bins = int(np.ceil(2 * self.lim / self.bin_w))

    # --- geometry ----------------------------------------------------------------------------
    def _zbuffer(self, seg: np.ndarray) -> np.ndarray:
        """Per azimuth bin (sensor frame), the range of the nearest occluding segment."""
        zb = np.full(self.n_bins, np.inf)
        if len(seg) == 0:
            return zb
        x0, y0, x1, y1 = seg.T
        a0, a1 = np.arctan2(y0, x0), np.arctan2(y1, x1)
        d = (a1 - a0 + np.pi) % (2 * np.pi) - np.pi
        lo = np.where(d >= 0, a0, a1)
        hi = lo + np.abs(d)
        lo_c, hi_c = np.maximum(lo, -self.lim), np.minimum(hi, self.lim)
        b0 = np.ceil((lo_c + self.lim) / self.bin_w - 0.5).astype(np.int64)
        b1 = np.floor((hi_c + self.lim) / self.bin_w - 0.5).astype(np.int64)
        count = np.where(lo_c < hi_c, np.maximum(b1 - b0 + 1, 0), 0)
        total = int(count.sum())
        if total == 0:
            return zb
        rep = np.repeat(np.arange(len(seg)), count)
        start = np.repeat(np.cumsum(count) - count, count)
        b = b0[rep] + (np.arange(total) - start)
        b = np.clip(b, 0, self.n_bins - 1)
        phi = -self.lim + (b + 0.5) * self.bin_w
        ex, ey = np.cos(phi), np.sin(phi)
        dx, dy = (x1 - x0)[rep], (y1 - y0)[rep]
        den = ex * dy - ey * dx
        with np.errstate(divide="ignore", invalid="ignore"):
            r = (x0[rep] * dy - y0[rep] * dx) / den
        r = np.where(np.isfinite(r) & (r > 0), r, np.inf)
        np.minimum.at(zb, b, r)
        return zb

    def _reach(self, az: np.ndarray) -> np.ndarray:
        cfg = self.cfg
        t = np.clip((np.abs(np.rad2deg(az)) - 40.0) / max(cfg.near_fov_deg - 40.0, 1e-6), 0, 1)
        return cfg.near_range_m - (cfg.near_range_m - cfg.near_edge_range_m) * t

    def chunk_view(
        self, static: Scatterers, occ: np.ndarray, refl: np.ndarray, sensor_xy, sensor_yaw: float
    ) -> tuple[Scatterers, np.ndarray, np.ndarray]:
        """What a sensor near ``sensor_xy`` / ``sensor_yaw`` can possibly see within ~1 s.

        A relaxed field of view (margins for up to ~15 m of travel and ~35 deg of turn) computed
        once per chunk of sweeps, so each sweep works on a small sector instead of the city.
        """
        cfg = self.cfg
        rot = rot2(-float(sensor_yaw))  # world -> sensor
        near_lim = np.deg2rad(cfg.near_fov_deg + 35.0)
        far_lim = np.deg2rad(cfg.far_fov_deg + 35.0)

        def keep(xy):
            p = (xy - sensor_xy) @ rot.T
            r = np.hypot(p[:, 0], p[:, 1])
            a = np.abs(np.arctan2(p[:, 1], p[:, 0]))
            return (
                (r < 30.0)
                | ((a < near_lim) & (r < cfg.near_range_m + 20.0))
                | ((a < far_lim) & (r < cfg.far_range_m + 20.0))
            )

        def keep_seg(sg):
            if len(sg) == 0:
                return sg
            m = keep(sg[:, :2]) | keep(sg[:, 2:]) | keep(0.5 * (sg[:, :2] + sg[:, 2:]))
            return sg[m]

        return static.subset(keep(static.xy)), keep_seg(occ), keep_seg(refl)

    # --- one sweep ---------------------------------------------------------------------------
    def sweep(
        self,
        world: SweepWorld,
        sensor_xy: np.ndarray,
        sensor_yaw: float,
        v_sensor: np.ndarray,
        rng: np.random.Generator,
        return_labels: bool = False,
    ):
        """Points (RADAR_DTYPE) of one sweep; ``v_sensor`` is the sensor's velocity over ground
        expressed in the sensor frame. With ``return_labels`` also the per-point truth
        (:data:`LABEL_DTYPE`, same order as the points)."""
        cfg = self.cfg
        noise = cfg.noise
        rot = rot2(-float(sensor_yaw))  # world -> sensor

        near_boxes = world.boxes
        if len(near_boxes):
            rb = (near_boxes.xy - sensor_xy) @ rot.T
            dist = np.hypot(rb[:, 0], rb[:, 1])
            azb = np.abs(np.arctan2(rb[:, 1], rb[:, 0]))
            near_boxes = near_boxes.subset(
                (dist < 15.0)
                | ((azb < np.deg2rad(cfg.near_fov_deg + 15.0)) & (dist < cfg.near_range_m + 10.0))
                | ((azb < np.deg2rad(cfg.far_fov_deg + 8.0)) & (dist < cfg.far_range_m + 10.0))
            )
        box_sc, box_vel, box_stop, box_occ = box_scatterers(near_boxes, rng)
        sc = Scatterers.concat([world.static, box_sc])
        n_static = len(world.static)
        vel_w = (
            np.vstack([np.zeros((n_static, 2)), box_vel])
            if len(box_sc)
            else np.zeros((n_static, 2))
        )
        stopped = (
            np.concatenate([np.zeros(n_static, bool), box_stop])
            if len(box_sc)
            else (np.zeros(n_static, bool))
        )

        rel = sc.xy - sensor_xy
        ps = rel @ rot.T
        r = np.hypot(ps[:, 0], ps[:, 1])
        az = np.arctan2(ps[:, 1], ps[:, 0])
        far_fov, near_fov = np.deg2rad(cfg.far_fov_deg), np.deg2rad(cfg.near_fov_deg)
        in_near = (np.abs(az) <= near_fov) & (r <= self._reach(az))
        in_far = (np.abs(az) <= far_fov) & (r <= cfg.far_range_m)
        cand = np.flatnonzero((in_near | in_far) & (r > 0.8))
        # Facing and specular lobe.
        nrm = sc.normal[cand]
        has_n = np.any(nrm != 0, axis=1)
        u_w = rel[cand] / r[cand, None]
        cos_inc = -np.einsum("ij,ij->i", nrm, u_w)
        facing = ~has_n | (cos_inc > 0.03)
        cand = cand[facing]
        nrm, has_n, cos_inc = nrm[facing], has_n[facing], cos_inc[facing]
        # Occlusion: test a point slightly in front of the surface (its own wall must not hide it).
        occ = np.vstack([world.occluders, box_occ]) if len(box_occ) else world.occluders
        occ_s = np.empty_like(occ)
        occ_s[:, :2] = (occ[:, :2] - sensor_xy) @ rot.T
        occ_s[:, 2:] = (occ[:, 2:] - sensor_xy) @ rot.T
        zb = self._zbuffer(occ_s)
        test = ps[cand] + (nrm @ rot.T) * 0.4
        rt = np.hypot(test[:, 0], test[:, 1])
        bt = np.clip(
            ((np.arctan2(test[:, 1], test[:, 0]) + self.lim) / self.bin_w).astype(np.int64),
            0,
            self.n_bins - 1,
        )
        visible = rt <= zb[bt] + 0.25
        cand, nrm, has_n, cos_inc = cand[visible], nrm[visible], has_n[visible], cos_inc[visible]
        # Radar cross-section now and detection probability.
        inc = np.arccos(np.clip(cos_inc, -1, 1))
        rcs = sc.rcs_dbsm[cand] + np.where(
            has_n, sc.spec_gain_db[cand] * np.exp(-((inc / sc.lobe_rad[cand]) ** 2)), 0.0
        )
        rcs = rcs + rng.normal(0, noise.rcs_spread_db, len(cand))
        rc, ac = r[cand], az[cand]
        snr = self._snr(rcs, rc, ac, in_far[cand])
        pd = sc.p_scale[cand] / (1.0 + np.exp(-snr / cfg.snr_width_db))
        det = rng.uniform(0, 1, len(cand)) < pd
        cand, rcs, snr = cand[det], rcs[det], snr[det]
        pos = ps[cand] + rng.normal(0, 1, (len(cand), 2)) * sc.jitter_m[cand, None]
        v_rel = vel_w[cand] @ rot.T - v_sensor
        kind = np.where(snr < 4.0, WEAK, REAL)
        cls = sc.cls[cand].astype(np.int64)
        stop = stopped[cand]

        # Multipath ghosts: mirror strong targets across a nearby facade or guard rail.
        gpos, gvel, grcs = self._mirror_ghosts(
            world.reflectors, sensor_xy, rot, pos, v_rel, v_sensor, rcs, rng
        )
        strong = np.flatnonzero((rcs > 8.0) & (np.hypot(pos[:, 0], pos[:, 1]) < 35.0))
        dbl = strong[rng.uniform(0, 1, len(strong)) < cfg.double_bounce_probability]
        # Clutter / low-quality clusters.
        clutter_rate = cfg.clutter_rate * self.clutter_scale
        n_cl = int(rng.poisson(clutter_rate * (1.0 - cfg.sidelobe_fraction)))
        cpos, cvel, crcs, ckind = self._clutter(n_cl, v_sensor, rng)
        # Sidelobe echoes: the range and Doppler of a real return at a wrong azimuth.
        n_sl = int(rng.poisson(clutter_rate * cfg.sidelobe_fraction)) if len(pos) else 0
        if n_sl:
            src = rng.integers(0, len(pos), n_sl)
            r_src = np.hypot(pos[src, 0], pos[src, 1])
            az_src = np.arctan2(pos[src, 1], pos[src, 0])
            u_src = np.column_stack([np.cos(az_src), np.sin(az_src)])
            vr_src = np.einsum("ij,ij->i", u_src, v_rel[src])
            off = rng.uniform(1.5, 5.0, n_sl) * rng.choice([-1.0, 1.0], n_sl)
            az_sl = az_src + np.deg2rad(off)
            u_sl = np.column_stack([np.cos(az_sl), np.sin(az_sl)])
            r_sl = np.maximum(r_src + rng.normal(0, 0.3, n_sl), 1.0)
            cpos = np.vstack([cpos, r_sl[:, None] * u_sl])
            cvel = np.vstack([cvel, vr_src[:, None] * u_sl])
            crcs = np.concatenate([crcs, rng.normal(2.5, 4.0, n_sl)])
            ckind = np.concatenate([ckind, np.full(n_sl, SIDELOBE)])

        all_pos = np.vstack([pos, gpos, 2 * pos[dbl], cpos])
        all_vrel = np.vstack([v_rel, gvel, 2 * v_rel[dbl], cvel])
        all_rcs = np.concatenate([rcs, grcs, rcs[dbl] - 12.0, crcs])
        all_kind = np.concatenate(
            [kind, np.full(len(gpos), MIRROR), np.full(len(dbl), DOUBLE), ckind]
        )
        all_cls = np.concatenate(
            [cls, np.full(len(gpos), GHOST), np.full(len(dbl), GHOST), np.full(len(cpos), CLUTTER)]
        )
        all_stop = np.concatenate([stop, np.zeros(len(gpos) + len(dbl) + len(cpos), bool)])
        rng_all = np.hypot(all_pos[:, 0], all_pos[:, 1])
        keep = (rng_all > 0.5) & (rng_all < cfg.far_range_m + 10.0)
        n = int(keep.sum())
        if n > cfg.max_points:
            # The sensor reports at most max_points clusters; real ones win more often.
            key = np.log(_SELECT_WEIGHT[all_kind]) + rng.gumbel(size=len(all_kind))
            key[~keep] = -np.inf
            sel = np.argsort(-key)[: cfg.max_points]
        else:
            sel = np.flatnonzero(keep)
        pts, order = self._fields(
            all_pos[sel],
            all_vrel[sel],
            all_rcs[sel],
            all_kind[sel],
            all_cls[sel],
            all_stop[sel],
            v_sensor,
            rng,
        )
        if not return_labels:
            return pts
        labels = np.zeros(len(pts), dtype=LABEL_DTYPE)
        labels["cls"] = all_cls[sel][order]
        labels["kind"] = all_kind[sel][order]
        labels["ground_speed_mps"] = np.linalg.norm(all_vrel[sel] + v_sensor, axis=1)[order]
        return pts, labels

    def _snr(self, rcs, r, az, in_far):
        cfg = self.cfg
        # Sensitivity time control: near-range gain is held down, so weak near clutter (leaves,
        # kerbs) does not swamp the cluster list.
        path = -40.0 * np.log10(np.maximum(r, cfg.stc_range_m) / 100.0)
        g_near = cfg.near_gain_db - self.near_rolloff_db * (az / np.deg2rad(cfg.near_fov_deg)) ** 2
        g_far = np.where(
            in_far, cfg.far_gain_db - 3.0 * (az / np.deg2rad(cfg.far_fov_deg)) ** 2, -np.inf
        )
        g_near = np.where(r <= self._reach(az), g_near, -np.inf)
        return rcs + path + np.maximum(g_near, g_far) + self.gain_db

    def _mirror_ghosts(self, refl, sensor_xy, rot, pos, v_rel, v_sensor, rcs, rng):
        cfg = self.cfg
        empty = (np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0))
        strong = np.flatnonzero(rcs > 3.0)
        if len(strong) == 0 or len(refl) == 0 or cfg.ghost_probability <= 0:
            return empty
        strong = strong[rng.uniform(0, 1, len(strong)) < cfg.ghost_probability * 2.5]
        if len(strong) == 0:
            return empty
        a = (refl[:, :2] - sensor_xy) @ rot.T
        b = (refl[:, 2:] - sensor_xy) @ rot.T
        mid = 0.5 * (a + b)
        near = np.flatnonzero(np.linalg.norm(mid, axis=1) < 120.0)
        if len(near) == 0:
            return empty
        a, b = a[near], b[near]
        p = pos[strong]
        d = b - a
        dd = np.einsum("ij,ij->i", d, d)
        # Nearest reflector to each strong target.
        t = np.clip(((p[:, None, :] - a[None]) * d[None]).sum(-1) / dd[None], 0, 1)
        closest = a[None] + t[..., None] * d[None]
        dist = np.linalg.norm(p[:, None, :] - closest, axis=-1)
        j = np.argmin(dist, axis=1)
        ok = dist[np.arange(len(p)), j] < 20.0
        aj, dj = a[j], d[j]
        nrm = np.column_stack([-dj[:, 1], dj[:, 0]]) / np.sqrt(dd[j])[:, None]
        side_p = np.einsum("ij,ij->i", p - aj, nrm)
        side_s = np.einsum("ij,ij->i", -aj, nrm)
        ok &= np.sign(side_p) == np.sign(side_s)  # target and sensor on the same side
        img = p - 2 * side_p[:, None] * nrm
        # The sensor->image ray must cross the reflector segment.
        den = img[:, 0] * dj[:, 1] - img[:, 1] * dj[:, 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            lam = (aj[:, 0] * dj[:, 1] - aj[:, 1] * dj[:, 0]) / den  # along sensor->image
            mu = (aj[:, 0] * img[:, 1] - aj[:, 1] * img[:, 0]) / den  # along the segment
        ok &= (lam > 0) & (lam < 1) & (mu >= 0) & (mu <= 1)
        if not ok.any():
            return empty
        img, nrm = img[ok], nrm[ok]
        vg = v_rel[strong[ok]] + v_sensor  # ground velocity in the sensor frame
        vg_m = vg - 2 * np.einsum("ij,ij->i", vg, nrm)[:, None] * nrm
        v_img = vg_m - v_sensor
        wrong = rng.uniform(0, 1, len(img)) < 0.3  # rough reflectors smear the Doppler
        v_img = v_img + wrong[:, None] * rng.normal(0, 2.5, v_img.shape)
        return img, v_img, rcs[strong[ok]] - rng.uniform(6, 15, len(img))

    def _clutter(self, n, v_sensor, rng):
        cfg = self.cfg
        far = rng.uniform(0, 1, n) < cfg.clutter_far_fraction
        az = np.where(
            far,
            rng.uniform(-1, 1, n) * np.deg2rad(cfg.far_fov_deg),
            rng.uniform(-1, 1, n) * np.deg2rad(cfg.near_fov_deg),
        )
        rmax = np.where(far, cfg.far_range_m, self._reach(az))
        rmin = np.where(far, 20.0, 3.0)
        r = np.sqrt(rng.uniform(0, 1, n) * (rmax**2 - rmin**2) + rmin**2)
        pos = np.column_stack([r * np.cos(az), r * np.sin(az)])
        random_v = rng.uniform(0, 1, n) < 0.18
        v = np.where(random_v[:, None], rng.normal(0, 4.0, (n, 2)), -v_sensor[None, :])
        rcs = rng.normal(2.5, 4.0, n)
        kind = np.where(random_v, CLUTTER_RANDOM, CLUTTER_STATIC)
        return pos, v, rcs, kind

    def _fields(self, pos, v_rel, rcs, kind, cls, stop, v_sensor, rng):
        cfg, noise = self.cfg, self.cfg.noise
        n = len(pos)
        out = np.zeros(n, dtype=RADAR_DTYPE)
        if n == 0:
            return out, np.zeros(0, np.int64)
        r = np.hypot(pos[:, 0], pos[:, 1])
        az = np.arctan2(pos[:, 1], pos[:, 0])
        sig_r = noise.range_std_m[0] + noise.range_std_m[1] * r
        sig_a = np.deg2rad(
            noise.azimuth_std_deg[0]
            + noise.azimuth_std_deg[1] * (az / np.deg2rad(cfg.near_fov_deg)) ** 2
        )
        rm = np.maximum(r + rng.normal(0, 1, n) * sig_r, 0.3)
        am = az + rng.normal(0, 1, n) * sig_a
        wild_az = rng.uniform(0, 1, n) < noise.azimuth_outlier_fraction
        am = am + wild_az * rng.normal(0, np.deg2rad(noise.azimuth_outlier_std_deg), n)
        x, y = rm * np.cos(am), rm * np.sin(am)
        if noise.position_quantum_m > 0:
            q = noise.position_quantum_m
            x, y = np.round(x / q) * q, np.round(y / q) * q
            tiny = (x == 0) & (y == 0)
            x[tiny] = q
        x32, y32 = x.astype(np.float32), y.astype(np.float32)
        xf, yf = x32.astype(np.float64), y32.astype(np.float64)
        rr = np.hypot(xf, yf)
        u = np.column_stack([xf / rr, yf / rr])
        up = np.column_stack([-u[:, 1], u[:, 0]])
        vr = (1.0 + noise.doppler_scale_error) * np.einsum("ij,ij->i", u, v_rel)
        vr = vr + rng.normal(0, noise.doppler_std_mps, n)
        wild_v = rng.uniform(0, 1, n) < noise.doppler_outlier_fraction
        vr = vr + wild_v * rng.normal(0, noise.doppler_outlier_std_mps, n)
        vt = np.einsum("ij,ij->i", up, v_rel) + rng.normal(0, noise.tangential_std_mps, n)
        v_raw = vr[:, None] * u + vt[:, None] * up
        if noise.velocity_quantum_mps > 0:
            v_raw = np.round(v_raw / noise.velocity_quantum_mps) * noise.velocity_quantum_mps
        v32 = v_raw.astype(np.float32)
        vq = v32.astype(np.float64)
        vr_q = np.einsum("ij,ij->i", u, vq)
        vr_comp = vr_q + u @ v_sensor
        v_comp = vr_comp[:, None] * u
        out["x"], out["y"] = x32, y32
        out["vx"], out["vy"] = v32[:, 0], v32[:, 1]
        out["vx_comp"], out["vy_comp"] = v_comp[:, 0], v_comp[:, 1]
        if cfg.gain_biases_rcs:
            rcs = rcs + self.gain_db
        rq = noise.rcs_quantum_db
        out["rcs"] = np.round(rcs / rq) * rq if rq > 0 else rcs
        # dyn_prop from the compensated Doppler (what the sensor itself can know).
        vg = v_rel + v_sensor
        vg_rad = np.einsum("ij,ij->i", u, vg)
        vg_tan = np.abs(np.einsum("ij,ij->i", up, vg))
        moving = np.abs(vr_comp) > 0.45
        draw = rng.uniform(0, 1, n)
        static_dp = np.where(draw < 0.62, 1, np.where(draw < 0.95, 3, 5))
        moving_dp = np.where(vg_tan > 2.0 * np.abs(vg_rad), 6, np.where(vr_comp > 0, 0, 2))
        dp = np.where(moving, moving_dp, static_dp)
        dp = np.where(stop & ~moving & (rng.uniform(0, 1, n) < 0.85), 7, dp)
        clutter = (kind == CLUTTER_STATIC) | (kind == CLUTTER_RANDOM) | (kind == SIDELOBE)
        dp = np.where(clutter & (rng.uniform(0, 1, n) < 0.15), 4, dp)
        dp = np.where(rng.uniform(0, 1, n) < 0.02, 4, dp)
        out["dyn_prop"] = dp
        # Quality fields per candidate kind (vectorised categorical draws).
        valid0 = rng.uniform(0, 1, n) < _INV_P0[kind]
        pick = (rng.uniform(0, 1, n)[:, None] > _INV_CUM[kind]).sum(1)
        inv = np.where(valid0, 0, _INV_STATES[kind, np.minimum(pick, _INV_STATES.shape[1] - 1)])
        bump = rng.integers(0, 3, n) * (rng.uniform(0, 1, n) < 0.4)
        pdh0 = np.clip(_PDH0_BASE[kind] + bump, 1, 7)
        inv = np.where((r < 2.0) & (inv == 0) & (rng.uniform(0, 1, n) < 0.5), 2, inv)
        out["invalid_state"] = inv
        out["pdh0"] = pdh0
        other = np.array([1, 2, 4, 4])[rng.integers(0, 4, n)]
        amb = np.where(rng.uniform(0, 1, n) < _AMBIG3[kind], 3, other)
        out["ambig_state"] = amb
        out["is_quality_valid"] = 1
        sx = np.hypot(sig_r * np.cos(az), r * sig_a * np.sin(az))
        sy = np.hypot(sig_r * np.sin(az), r * sig_a * np.cos(az))
        out["x_rms"] = rms_code(sx)
        out["y_rms"] = rms_code(sy)
        sd, st = noise.doppler_std_mps + 0.05, noise.tangential_std_mps + 0.1
        out["vx_rms"] = rms_code(np.hypot(sd * np.cos(az), st * np.sin(az)))
        out["vy_rms"] = rms_code(np.hypot(sd * np.sin(az), st * np.cos(az)))
        order = np.argsort(rr, kind="stable")
        out = out[order]
        out["id"] = np.arange(n)
        return out, order
