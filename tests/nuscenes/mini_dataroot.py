"""A hand-made nuScenes-layout dataroot for the reader tests (independent of radarslam.sim).

World: static landmarks (poles) along an arc the ego drives at constant speed and yaw rate, plus
seeded random clutter with every state value. Five radars with nuScenes-like mounts sweep at
13 Hz with per-channel phase offsets and jitter; key frames at 2 Hz (the sweep nearest to each
sample time). Landmark points are exact (sensor frame, z = 0) and carry the physical relative
velocity of a static target (-v_sensor in the sensor frame, v_comp = 0), so accumulation and
velocity rotation can be checked against the truth kept in :class:`MiniTruth`.

Also writes the near-empty tables and the map PNG the devkit's ``NuScenes`` class needs.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from radarslam.geometry import rotation_to_quat, se2_to_matrix
from radarslam.nuscenes.pcd import pcd_bytes
from radarslam.types import RADAR_CHANNELS, RADAR_DTYPE

VERSION = "v1.0-mini"
PERIOD_US = 76_923
#: nuScenes-like radar mounts in the ego frame: (x, y, yaw_deg)
MOUNTS = {
    "RADAR_FRONT": (3.41, 0.0, 0.0),
    "RADAR_FRONT_LEFT": (2.42, 0.80, 88.0),
    "RADAR_FRONT_RIGHT": (2.42, -0.80, -89.0),
    "RADAR_BACK_LEFT": (-0.56, 0.62, 178.0),
    "RADAR_BACK_RIGHT": (-0.56, -0.62, -178.0),
}
PHASE_US = {
    "RADAR_FRONT": 0,
    "RADAR_FRONT_LEFT": 11_000,
    "RADAR_FRONT_RIGHT": 23_000,
    "RADAR_BACK_LEFT": 31_000,
    "RADAR_BACK_RIGHT": -17_000,
}
SENSOR_Z = 0.5


def tok(*parts) -> str:
    return hashlib.md5("/".join(str(p) for p in parts).encode()).hexdigest()


@dataclass(frozen=True)
class SceneSpec:
    name: str
    log: str  # log key in LOGS
    start_us: int
    duration_s: float = 3.0
    # (channel, t_from_s, t_to_s): no sweeps of that channel in that stretch (relative to start)
    gaps: tuple[tuple[str, float, float], ...] = ()
    empty_sweeps: int = 0  # how many sweeps (RADAR_BACK_LEFT) are written with POINTS 0
    nan_points: int = 0  # how many sweeps (RADAR_FRONT_RIGHT) carry one NaN point


LOGS = {
    "logA": ("boston-seaport", "2018-07-24", "n015"),
    "logB": ("singapore-onenorth", "2018-08-01", "n008"),
    "logC": ("boston-seaport", "2018-08-30", "n015"),
}

DEFAULT_SCENES = (
    # scene.json order is deliberately not the time order
    SceneSpec("scene-0004", "logC", 1_535_600_000_000_000),
    SceneSpec("scene-0002", "logA", 1_532_402_000_000_000, empty_sweeps=2, nan_points=3),
    SceneSpec(
        "scene-0001",
        "logA",
        1_532_401_000_000_000,
        gaps=(("RADAR_FRONT", 1.05, 1.95),),
    ),
    SceneSpec("scene-0003", "logB", 1_533_100_000_000_000),
)


@dataclass
class MiniTruth:
    dataroot: Path
    landmarks_world: np.ndarray  # (L, 3)
    world_from_sensor: dict[str, np.ndarray] = field(default_factory=dict)  # sd token -> 4x4
    sensor_velocity_world: dict[str, np.ndarray] = field(default_factory=dict)  # sd token -> (3,)
    landmark_ids: dict[str, np.ndarray] = field(
        default_factory=dict
    )  # sd token -> ids in file order
    num_landmark_points: dict[str, int] = field(default_factory=dict)  # sd token -> count
    sweeps: dict[tuple[str, str], list[str]] = field(default_factory=dict)  # (scene, ch) -> tokens
    samples: dict[str, list[str]] = field(default_factory=dict)  # scene -> sample tokens
    keyframes: dict[str, dict[str, str]] = field(default_factory=dict)  # sample -> ch -> sd token
    empty_tokens: list[str] = field(default_factory=list)
    nan_tokens: list[str] = field(default_factory=list)


def ego_pose(t_s: float, speed=8.0, yaw_rate=0.12, offset=(0.0, 0.0, 0.3)):
    """(world_from_ego, v_ego_world (2,), yaw_rate) on an arc."""
    yaw = offset[2] + yaw_rate * t_s
    r = speed / yaw_rate
    x = offset[0] + r * (np.sin(yaw) - np.sin(offset[2]))
    y = offset[1] - r * (np.cos(yaw) - np.cos(offset[2]))
    return se2_to_matrix(x, y, yaw), speed * np.array([np.cos(yaw), np.sin(yaw)]), yaw_rate


def ego_from_sensor(channel: str) -> np.ndarray:
    x, y, yaw_deg = MOUNTS[channel]
    pose = se2_to_matrix(x, y, np.deg2rad(yaw_deg))
    pose[2, 3] = SENSOR_Z
    return pose


def make_landmarks(rng: np.random.Generator) -> np.ndarray:
    # poles on both sides of the road, 6-25 m from the centre line
    pts = []
    for t_s in np.linspace(-2.0, 12.0, 60):
        pose, _, _ = ego_pose(t_s)
        left = pose[:2, 1]
        for side in (-1, 1):
            d = side * rng.uniform(6.0, 25.0)
            p = pose[:2, 3] + left * d + pose[:2, 0] * rng.uniform(-3, 3)
            pts.append([p[0], p[1], SENSOR_Z])
    return np.asarray(pts)


def _sweep_points(rng, truth_lm, world_from_sensor, v_sensor_world, lm_ids_out):
    sensor_from_world = np.linalg.inv(world_from_sensor)
    p = truth_lm @ sensor_from_world[:3, :3].T + sensor_from_world[:3, 3]
    rng_m = np.hypot(p[:, 0], p[:, 1])
    az = np.arctan2(p[:, 1], p[:, 0])
    vis = (p[:, 0] > 0.5) & (np.abs(az) < np.deg2rad(60)) & (rng_m < 80.0) & (rng_m > 2.0)
    ids = np.flatnonzero(vis)[:90]
    n_lm = len(ids)
    n_cl = int(rng.integers(10, 30))
    pts = np.zeros(n_lm + n_cl, dtype=RADAR_DTYPE)
    v_s = sensor_from_world[:3, :3] @ v_sensor_world  # sensor velocity in the sensor frame
    # landmarks: exact, static
    pts["x"][:n_lm] = p[ids, 0]
    pts["y"][:n_lm] = p[ids, 1]
    pts["z"][:n_lm] = 0.0
    pts["vx"][:n_lm] = -v_s[0]
    pts["vy"][:n_lm] = -v_s[1]
    pts["dyn_prop"][:n_lm] = rng.choice([1, 3], n_lm, p=[0.8, 0.2])
    pts["invalid_state"][:n_lm] = 0
    pts["ambig_state"][:n_lm] = 3
    pts["rcs"][:n_lm] = rng.normal(6.0, 5.0, n_lm)
    # clutter: random everything
    r = rng.uniform(1.2, 90.0, n_cl)
    a = rng.uniform(-np.pi / 3, np.pi / 3, n_cl)
    x, y = r * np.cos(a), r * np.sin(a)
    x[:2] = rng.uniform(0.2, 0.9, 2)  # two points inside the 1 m remove_close square
    y[:2] = rng.uniform(-0.9, 0.9, 2)
    vr = rng.normal(0.0, 5.0, n_cl)
    u = np.column_stack([x, y]) / np.hypot(x, y)[:, None]
    v_raw = -v_s[:2][None, :] + u * vr[:, None]
    c = slice(n_lm, None)
    pts["x"][c], pts["y"][c] = x, y
    pts["vx"][c], pts["vy"][c] = v_raw[:, 0], v_raw[:, 1]
    pts["vx_comp"][c], pts["vy_comp"][c] = u[:, 0] * vr, u[:, 1] * vr
    pts["dyn_prop"][c] = rng.integers(0, 8, n_cl)
    pts["invalid_state"][c] = rng.choice([0, 4, 9, 11, 16], n_cl)
    pts["ambig_state"][c] = rng.choice([1, 2, 3, 4], n_cl)
    pts["rcs"][c] = rng.normal(0.0, 6.0, n_cl)
    pts["id"] = np.arange(len(pts))
    pts["pdh0"] = rng.integers(0, 8, len(pts))
    pts["is_quality_valid"] = 1
    pts["x_rms"], pts["y_rms"] = rng.integers(0, 20, len(pts)), rng.integers(0, 20, len(pts))
    pts["vx_rms"], pts["vy_rms"] = rng.integers(0, 20, len(pts)), rng.integers(0, 20, len(pts))
    lm_ids_out.append(ids)
    return pts, n_lm


def build_mini_dataroot(root: str | Path, scenes=DEFAULT_SCENES, seed: int = 7) -> MiniTruth:
    root = Path(root)
    rng = np.random.default_rng(seed)
    landmarks = make_landmarks(rng)
    truth = MiniTruth(dataroot=root, landmarks_world=landmarks)
    tables: dict[str, list] = {
        k: []
        for k in (
            "scene", "sample", "sample_data", "ego_pose", "calibrated_sensor", "sensor", "log",
            "attribute", "category", "instance", "sample_annotation", "visibility", "map",
        )
    }  # fmt: skip
    for key, (location, date, vehicle) in LOGS.items():
        tables["log"].append(
            {
                "token": tok("log", key),
                "logfile": f"{vehicle}-{date}-{key}",
                "vehicle": vehicle,
                "date_captured": date,
                "location": location,
            }
        )
    for ch in (*RADAR_CHANNELS, "LIDAR_TOP"):
        tables["sensor"].append(
            {
                "token": tok("sensor", ch),
                "channel": ch,
                "modality": "lidar" if "LIDAR" in ch else "radar",
            }
        )
    cs_tok = {}
    for key in LOGS:
        for ch in (*RADAR_CHANNELS, "LIDAR_TOP"):
            pose = ego_from_sensor(ch) if ch in MOUNTS else np.eye(4)
            cs_tok[(key, ch)] = tok("cs", key, ch)
            tables["calibrated_sensor"].append(
                {
                    "token": cs_tok[(key, ch)],
                    "sensor_token": tok("sensor", ch),
                    "translation": pose[:3, 3].tolist(),
                    "rotation": rotation_to_quat(pose[:3, :3]).tolist(),
                    "camera_intrinsic": [],
                }
            )
    (root / "maps").mkdir(parents=True, exist_ok=True)
    _write_png(root / "maps" / "blank.png")
    tables["map"].append(
        {
            "token": tok("map"),
            "category": "semantic_prior",
            "filename": "maps/blank.png",
            "log_tokens": [tok("log", k) for k in LOGS],
        }
    )
    tables["category"].append({"token": tok("cat"), "name": "vehicle.car", "description": ""})
    tables["visibility"].append({"token": "1", "level": "v0-40", "description": ""})

    for spec in scenes:
        _build_scene(root, spec, rng, truth, tables, cs_tok)

    vdir = root / VERSION
    vdir.mkdir(parents=True, exist_ok=True)
    for name, recs in tables.items():
        (vdir / f"{name}.json").write_text(json.dumps(recs, indent=0))
    return truth


def _write_png(path: Path) -> None:
    from PIL import Image

    Image.fromarray(np.zeros((8, 8), dtype=np.uint8)).save(path)


def _build_scene(root, spec: SceneSpec, rng, truth: MiniTruth, tables, cs_tok) -> None:
    scene_token = tok("scene", spec.name)
    logkey = spec.log
    _, _, vehicle = LOGS[logkey]
    # samples (lidar key frames) at 2 Hz
    n_samples = int(spec.duration_s * 2)
    sample_times = [spec.start_us + 250_000 + 500_000 * i for i in range(n_samples)]
    sample_toks = [tok("sample", spec.name, i) for i in range(n_samples)]
    for i, (st, ts) in enumerate(zip(sample_toks, sample_times, strict=True)):
        tables["sample"].append(
            {
                "token": st,
                "timestamp": ts,
                "prev": sample_toks[i - 1] if i else "",
                "next": sample_toks[i + 1] if i + 1 < n_samples else "",
                "scene_token": scene_token,
            }
        )
        # a lidar key frame per sample: non-radar records the reader must skip
        sd = tok("lidar", spec.name, i)
        tables["sample_data"].append(
            {
                "token": sd,
                "sample_token": st,
                "ego_pose_token": sd,
                "calibrated_sensor_token": cs_tok[(logkey, "LIDAR_TOP")],
                "timestamp": ts,
                "fileformat": "pcd",
                "is_key_frame": True,
                "height": 0,
                "width": 0,
                "filename": f"samples/LIDAR_TOP/{vehicle}__LIDAR_TOP__{ts}.pcd.bin",
                "prev": tok("lidar", spec.name, i - 1) if i else "",
                "next": tok("lidar", spec.name, i + 1) if i + 1 < n_samples else "",
            }
        )
        pose, _, _ = ego_pose((ts - spec.start_us) * 1e-6)
        tables["ego_pose"].append(_ego_record(sd, ts, pose))
    truth.samples[spec.name] = sample_toks
    tables["scene"].append(
        {
            "token": scene_token,
            "log_token": tok("log", logkey),
            "nbr_samples": n_samples,
            "first_sample_token": sample_toks[0],
            "last_sample_token": sample_toks[-1],
            "name": spec.name,
            "description": f"synthetic {spec.name}",
        }
    )

    end_us = spec.start_us + int(spec.duration_s * 1e6)
    for ch in RADAR_CHANNELS:
        times = []
        t = spec.start_us + 40_000 + PHASE_US[ch]
        while t < end_us:
            jitter = int(rng.integers(-1500, 1500))
            rel = (t - spec.start_us) * 1e-6
            if not any(g == ch and a <= rel < b for g, a, b in spec.gaps):
                times.append(t + jitter)
            t += PERIOD_US
        # key frames: the sweep nearest to each sample time (if within a period)
        key_idx = {}
        tarr = np.asarray(times)
        for si, ts in enumerate(sample_times):
            j = int(np.argmin(np.abs(tarr - ts)))
            if abs(tarr[j] - ts) < PERIOD_US // 2 + 2000:
                key_idx[j] = si
        toks = [tok("radar", spec.name, ch, k) for k in range(len(times))]
        truth.sweeps[(spec.name, ch)] = toks
        for k, (ts, sd) in enumerate(zip(times, toks, strict=True)):
            is_key = k in key_idx
            si = key_idx[k] if is_key else int(np.argmin(np.abs(np.asarray(sample_times) - ts)))
            folder = "samples" if is_key else "sweeps"
            filename = f"{folder}/{ch}/{vehicle}__{ch}__{ts}.pcd"
            pose, v_ego, w = ego_pose((ts - spec.start_us) * 1e-6)
            e_from_s = ego_from_sensor(ch)
            w_from_s = pose @ e_from_s
            r = pose[:2, :2] @ e_from_s[:2, 3]
            v_s = np.array([v_ego[0] - w * r[1], v_ego[1] + w * r[0], 0.0])
            ids_out: list = []
            pts, n_lm = _sweep_points(rng, truth.landmarks_world, w_from_s, v_s, ids_out)
            if ch == "RADAR_BACK_LEFT" and k in range(3, 3 + spec.empty_sweeps):
                pts, n_lm, ids_out = pts[:0], 0, [np.zeros(0, dtype=int)]
                truth.empty_tokens.append(sd)
            if ch == "RADAR_FRONT_RIGHT" and k in range(5, 5 + spec.nan_points):
                pts[-1]["vx_comp"] = np.nan  # a clutter point
                truth.nan_tokens.append(sd)
            path = root / filename
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(pcd_bytes(pts, padding=int(rng.integers(1, 400))))
            truth.world_from_sensor[sd] = w_from_s
            truth.sensor_velocity_world[sd] = v_s
            truth.landmark_ids[sd] = ids_out[0]
            truth.num_landmark_points[sd] = n_lm
            if is_key:
                truth.keyframes.setdefault(sample_toks[si], {})[ch] = sd
            tables["sample_data"].append(
                {
                    "token": sd,
                    "sample_token": sample_toks[si],
                    "ego_pose_token": tok("ego", sd),
                    "calibrated_sensor_token": cs_tok[(logkey, ch)],
                    "timestamp": ts,
                    "fileformat": "pcd",
                    "is_key_frame": is_key,
                    "height": 0,
                    "width": 0,
                    "filename": filename,
                    "prev": toks[k - 1] if k else "",
                    "next": toks[k + 1] if k + 1 < len(toks) else "",
                }
            )
            tables["ego_pose"].append(_ego_record(tok("ego", sd), ts, pose))


def _ego_record(token: str, ts: int, pose: np.ndarray) -> dict:
    return {
        "token": token,
        "timestamp": ts,
        "rotation": rotation_to_quat(pose[:3, :3]).tolist(),
        "translation": pose[:3, 3].tolist(),
    }
