"""Generate a synthetic dataroot in the exact nuScenes layout.

Order of writing: radar .pcd files and per-log sidecars first (workers, one log each), then the
tables, then ``synthetic/summary.json``. A run that was interrupted therefore lacks tables or the
summary and is detected by :func:`is_complete`.
"""

from __future__ import annotations

import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from radarslam.config import dump_config
from radarslam.errors import ConfigError
from radarslam.io.atomic import write_json_atomic, write_text_atomic
from radarslam.nuscenes.pcd import pcd_bytes
from radarslam.sim.config import SimConfig, load_sim_config
from radarslam.sim.ego import TumEgo, canonical_routes, extend_route, read_tum
from radarslam.sim.radar import (
    LABEL_DTYPE,
    NUSCENES_MOUNTS,
    RadarModel,
    SweepWorld,
    box_scatterers,
)
from radarslam.sim.traffic import EGO_START_S, EgoMotion, simulate_traffic
from radarslam.sim.world import (
    Scatterers,
    StaticWorld,
    build_world,
    drivable_mask,
    parked_cars,
)
from radarslam.sim.writer import (
    add_days,
    calibrated_sensor_record,
    log_start,
    make_token,
    pose_record,
    static_tables,
    write_map,
)
from radarslam.types import RADAR_DTYPE

CHANNELS = tuple(m.channel for m in NUSCENES_MOUNTS)
TABLES = (
    "attribute",
    "calibrated_sensor",
    "category",
    "ego_pose",
    "instance",
    "log",
    "map",
    "sample",
    "sample_annotation",
    "sample_data",
    "scene",
    "sensor",
    "visibility",
)


@dataclass
class SimulationSummary:
    dataroot: str
    version: str
    preset: str
    seed: int
    n_logs: int
    n_days: int
    n_scenes: int
    n_samples: int
    n_sweeps: int
    n_points: int
    bytes_written: int
    seconds: float
    per_log: list[dict] = field(default_factory=list)

    @property
    def sweeps_per_s(self) -> float:
        return self.n_sweeps / max(self.seconds, 1e-9)


@dataclass
class LogPlan:
    index: int
    token: str
    name: str
    date: str
    day: int
    start_us: int
    route_index: int
    reversed: bool
    ego_speed_mps: float
    scene_windows: list[tuple[float, float]]
    first_scene_number: int = 1  # scene names run scene-0001, scene-0002, ... over all logs


def is_complete(dataroot: str | Path, version: str) -> bool:
    """True when a generation run finished (its summary is written after every table)."""
    root = Path(dataroot)
    return (root / "synthetic" / "summary.json").is_file() and all(
        (root / version / f"{t}.json").is_file() for t in TABLES
    )


# --- planning ------------------------------------------------------------------------------------
def _world_for(cfg: SimConfig) -> tuple[StaticWorld, np.ndarray | None]:
    tum = read_tum(cfg.ego.trajectory_tum) if cfg.ego.trajectory_tum else None
    city = cfg.city
    if tum is not None:
        # Build the city around the given trajectory, then clear a corridor along it.
        lo, hi = tum[:, 1:3].min(0), tum[:, 1:3].max(0)
        mean_block = 0.5 * (city.block_min_m + city.block_max_m)
        nbx = int(np.clip(np.ceil((hi[0] - lo[0] + 300) / mean_block), 2, 60))
        nby = int(np.clip(np.ceil((hi[1] - lo[1] + 300) / mean_block), 2, 60))
        city = city.model_copy(
            update={
                "n_blocks_x": nbx,
                "n_blocks_y": nby,
                "origin_m": (float(lo[0] - 150), float(lo[1] - 150)),
            }
        )
    world = build_world(city, cfg.seed, cfg.traffic.light_cycle_s)
    if tum is not None:
        world = _carve_corridor(world, tum[:, 1:3], 9.0)
    return world, tum


def _carve_corridor(world: StaticWorld, xy: np.ndarray, half_width: float) -> StaticWorld:
    from scipy.spatial import cKDTree

    seg = np.diff(xy, axis=0)
    n = np.maximum(np.ceil(np.linalg.norm(seg, axis=1) / 0.5).astype(int), 1)
    dense = np.vstack(
        [xy[i] + np.linspace(0, 1, k, endpoint=False)[:, None] * seg[i] for i, k in enumerate(n)]
        + [xy[-1:]]
    )
    tree = cKDTree(dense)
    keep_sc = tree.query(world.scatterers.xy)[0] > half_width

    def seg_keep(s):
        if len(s) == 0:
            return np.zeros(0, bool)
        t = np.linspace(0, 1, 9)
        pts = s[:, None, :2] + t[None, :, None] * (s[:, None, 2:] - s[:, None, :2])
        d = tree.query(pts.reshape(-1, 2))[0].reshape(len(s), -1)
        return d.min(1) > half_width

    occ, refl = world.occluders, world.reflectors
    return StaticWorld(
        world.config,
        world.network,
        world.scatterers.subset(keep_sc),
        occ[seg_keep(occ)],
        refl[seg_keep(refl)],
        world.parking,
        world.buildings,
        world.bounds,
    )


def plan_logs(cfg: SimConfig, duration_s: float | None = None) -> list[LogPlan]:
    sch = cfg.schedule
    rng = np.random.default_rng([cfg.seed, 303])
    if sch.n_logs <= sch.n_days:
        days = np.sort(rng.choice(sch.n_days, sch.n_logs, replace=False))
    else:
        days = np.sort(rng.integers(0, sch.n_days, sch.n_logs))
    plans = []
    for i in range(sch.n_logs):
        date = add_days(sch.start_date, int(days[i]))
        start_us, name = log_start(date, float(rng.uniform(8 * 3600, 18 * 3600)))
        route_index = i % sch.n_routes
        reverse = bool(rng.uniform() < sch.reverse_fraction)
        if i == 1 and sch.reverse_fraction > 0 and sch.n_routes == 1:
            reverse = True  # two logs on one route: one drives it the other way round
        if i == sch.n_routes and sch.reverse_fraction > 0:
            reverse = True  # the first revisit of route 0 is in the opposite direction
        windows, t = [], float(rng.uniform(0.5, 3.0))
        for _ in range(sch.scenes_per_log):
            end = t + sch.scene_duration_s
            if duration_s is not None and end > duration_s - 0.2:
                end = min(end, duration_s - 0.2)
                if end - t >= min(2.0, sch.scene_duration_s):
                    windows.append((t, end))
                break
            windows.append((t, end))
            t = end + float(rng.uniform(*sch.scene_gap_s))
        if not windows:
            raise ConfigError(
                f"trajectory of {duration_s:.1f} s is too short for one scene; need >= 3 s"
            )
        plans.append(
            LogPlan(
                i,
                make_token(cfg.seed, "log", i),
                name,
                date,
                int(days[i]),
                start_us,
                route_index,
                reverse,
                float(rng.uniform(*cfg.ego.desired_speed_mps)),
                windows,
            )
        )
    number = 1
    for p in plans:
        p.first_scene_number = number
        number += len(p.scene_windows)
    return plans


# --- one log --------------------------------------------------------------------------------------
_WORLD_CACHE: dict[str, tuple[StaticWorld, np.ndarray | None]] = {}


def _cached_world(cfg: SimConfig):
    key = cfg.model_dump_json()
    if key not in _WORLD_CACHE:
        _WORLD_CACHE.clear()
        _WORLD_CACHE[key] = _world_for(cfg)
    return _WORLD_CACHE[key]


def _in_window(windows, t: float, log: int) -> bool:
    return any(w.start_s <= t < w.end_s and (w.log is None or w.log == log) for w in windows)


def _preselect(world: StaticWorld, lo, hi, extra_sc: Scatterers, extra_occ: np.ndarray):
    sc = Scatterers.concat([world.scatterers, extra_sc])
    m = np.all((sc.xy >= lo) & (sc.xy <= hi), axis=1)

    def segs(s):
        a = np.minimum(s[:, :2], s[:, 2:])
        b = np.maximum(s[:, :2], s[:, 2:])
        return s[np.all((b >= lo) & (a <= hi), axis=1)]

    occ = np.vstack([world.occluders, extra_occ])
    return sc.subset(m), segs(occ), segs(world.reflectors)


def _sensor_states(ego: EgoMotion, mounts_xy: tuple[float, float], mount_yaw: float):
    """World pose and sensor-frame velocity over ground of one radar for each ego state."""
    c, s = np.cos(ego.yaw), np.sin(ego.yaw)
    mx, my = mounts_xy
    sxy = ego.xy + np.column_stack([c * mx - s * my, s * mx + c * my])
    syaw = ego.yaw + mount_yaw
    # Velocity of the mounting point in the ego frame: v_ego + omega x lever arm.
    vx_e = ego.v_fwd_mps - ego.yaw_rate_radps * my
    vy_e = ego.v_lat_mps + ego.yaw_rate_radps * mx
    cm, sm = np.cos(mount_yaw), np.sin(mount_yaw)
    v_s = np.column_stack([cm * vx_e + sm * vy_e, -sm * vx_e + cm * vy_e])
    return sxy, syaw, v_s


def simulate_log(cfg: SimConfig, plan: LogPlan, dataroot: str) -> dict:
    """Simulate and write one log's radar files; returns its table records and statistics."""
    world, tum = _cached_world(cfg)
    seed = cfg.seed
    root = Path(dataroot)
    rng = np.random.default_rng([seed, 404, plan.index])
    mounts = NUSCENES_MOUNTS
    ego_from_sensor = {m.channel: m.ego_from_sensor() for m in mounts}
    t_end = plan.scene_windows[-1][1] + 1.0
    if tum is not None:
        ego_src = TumEgo(tum)
        lo, hi = tum[:, 1:3].min(0), tum[:, 1:3].max(0)
        margin = cfg.traffic.region_margin_m
        region = (lo[0] - margin, lo[1] - margin, hi[0] + margin, hi[1] + margin)
        traffic = simulate_traffic(
            world.network,
            cfg.traffic,
            cfg.ego,
            rng,
            t_end,
            None,
            0.0,
            0.0,
            world.config.facade_offset_m,
            region,
        )
        ego_fn = ego_src.ego
    else:
        route_rng = np.random.default_rng([seed, 505])
        routes = canonical_routes(
            world.network, route_rng, cfg.schedule.n_routes, cfg.schedule.route_length_m
        )
        route = routes[plan.route_index]
        pts = world.network.nodes[route]
        cum = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        fo = world.config.facade_offset_m
        start_along = fo
        if plan.reversed:
            # Drive back over the section the forward logs drive (revisits the other way).
            # (the ego rolls EGO_START_S before time 0 in both logs)
            expected = 4.5 * (t_end + 2 * EGO_START_S) * rng.uniform(0.9, 1.1)
            k = min(max(int(np.searchsorted(cum, expected)), 1), len(route) - 1)
            edge = cum[k] - cum[k - 1]
            start_along = float(np.clip(cum[k] - expected, fo, max(edge - fo - 5.0, fo)))
            route = route[: k + 1][::-1]
        else:
            # Logs of one route enter it at different points: overlapping, not identical.
            # The first log of a route starts at its beginning (where reversed logs end).
            first = plan.index < cfg.schedule.n_routes
            route = route[0 if first else int(rng.integers(0, max(len(route) // 4, 1))) :]
        need = cfg.ego.max_speed_mps * (t_end + 10.0) + 300.0
        route = extend_route(world.network, rng, route, need)
        pts = world.network.nodes[route]
        cum = np.concatenate([[0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        likely = pts[: int(np.searchsorted(cum, 0.7 * need)) + 2]
        margin = cfg.traffic.region_margin_m
        region = (
            likely[:, 0].min() - margin,
            likely[:, 1].min() - margin,
            likely[:, 0].max() + margin,
            likely[:, 1].max() + margin,
        )
        ego_v0 = min(plan.ego_speed_mps, cfg.ego.max_speed_mps)
        traffic = simulate_traffic(
            world.network,
            cfg.traffic,
            cfg.ego,
            rng,
            t_end,
            route,
            start_along,
            ego_v0,
            world.config.facade_offset_m,
            region,
        )
        ego_fn = traffic.ego
    parked = parked_cars(world, plan.day, seed)
    # Parked cars are static for the whole log: their scatterers join the static world once.
    car_rng = np.random.default_rng([seed, 707, plan.day])
    parked_sc, _, _, parked_occ = box_scatterers(parked, car_rng)
    model = RadarModel(cfg.radar)

    # Sweep clocks: every radar its own period, phase and jitter.
    clocks = {}
    for m in mounts:
        period = cfg.radar.period_s + rng.normal(0, cfg.radar.period_spread_s)
        phase = rng.uniform(0, period)
        ticks = np.arange(int(t_end / period) + 2)
        t = phase + ticks * period + rng.normal(0, cfg.radar.jitter_s, len(ticks))
        clocks[m.channel] = np.sort(t)

    records: dict[str, list[dict]] = {n: [] for n in ("scene", "sample", "sample_data", "ego_pose")}
    cs_records = []
    cs_token = {}
    for m in mounts:
        tok = make_token(seed, "calibrated_sensor", plan.index, m.channel)
        cs_token[m.channel] = tok
        cs_records.append(
            calibrated_sensor_record(
                tok, make_token(seed, "sensor", m.channel), ego_from_sensor[m.channel]
            )
        )
    side: dict[str, list] = {
        "token": [],
        "timestamp_us": [],
        "channel": [],
        "v_sensor": [],
        "ego_speed": [],
        "yaw_rate": [],
        "n_points": [],
    }
    n_points = 0
    n_bytes = 0
    label_parts: list[np.ndarray] = []
    pad_rng = np.random.default_rng([seed, 606, plan.index])
    far = cfg.radar.far_range_m + 10.0
    for j, (ts, te) in enumerate(plan.scene_windows):
        scene_no = plan.first_scene_number + j
        scene_tok = make_token(seed, "scene", plan.index, j)
        n_smp = int(np.floor((te - ts - 0.1) / cfg.schedule.sample_period_s)) + 1
        t_smp = ts + 0.05 + np.arange(n_smp) * cfg.schedule.sample_period_s
        t_smp = t_smp + rng.normal(0, 0.002, n_smp)
        smp_tok = [make_token(seed, "sample", plan.index, j, i) for i in range(n_smp)]
        for i in range(n_smp):
            records["sample"].append(
                {
                    "token": smp_tok[i],
                    "timestamp": plan.start_us + round(t_smp[i] * 1e6),
                    "prev": smp_tok[i - 1] if i > 0 else "",
                    "next": smp_tok[i + 1] if i + 1 < n_smp else "",
                    "scene_token": scene_tok,
                }
            )
        records["scene"].append(
            {
                "token": scene_tok,
                "log_token": plan.token,
                "nbr_samples": n_smp,
                "first_sample_token": smp_tok[0],
                "last_sample_token": smp_tok[-1],
                "name": f"scene-{scene_no:04d}",
                "description": f"synthetic, {plan.date}, "
                f"route {plan.route_index}{' reversed' if plan.reversed else ''}",
            }
        )
        # Static world near this scene's path.
        t_grid = np.linspace(ts, te, 41)
        path_xy = ego_fn(t_grid).xy
        lo, hi = path_xy.min(0) - far, path_xy.max(0) + far
        static, occ, refl = _preselect(world, lo, hi, parked_sc, parked_occ)
        for m in mounts:
            ch = m.channel
            t_all = clocks[ch]
            # Sweeps from just before the first key frame to half a sample period after the last.
            t_sw = t_all[(t_all >= t_smp[0] - 0.05) & (t_all < t_smp[-1] + 0.25)]
            t_sw = np.array(
                [
                    t
                    for t in t_sw
                    if not any(
                        w.channel == ch
                        for w in cfg.scenario.missing_radar
                        if w.start_s <= t < w.end_s and (w.log is None or w.log == plan.index)
                    )
                ]
            )
            if len(t_sw) == 0:
                continue
            # Key frame per sample: the sweep nearest the sample time.
            key_of = {}
            for i, tsmp in enumerate(t_smp):
                nearest = int(np.argmin(np.abs(t_sw - tsmp)))
                if abs(t_sw[nearest] - tsmp) <= 0.6 * cfg.radar.period_s:
                    key_of[nearest] = i
            # As in nuScenes, a radar's chain in a scene starts with its first key frame.
            if key_of:
                start = min(key_of)
                t_sw = t_sw[start:]
                key_of = {k - start: i for k, i in key_of.items()}
            ego = ego_fn(t_sw)
            sxy, syaw, v_s = _sensor_states(ego, (m.x_m, m.y_m), np.deg2rad(m.yaw_deg))
            sd_tok = [
                make_token(seed, "sample_data", plan.index, j, ch, k) for k in range(len(t_sw))
            ]
            chunk = 13  # ~1 s of sweeps share one pre-culled view of the static world
            for k, t in enumerate(t_sw):
                if k % chunk == 0:
                    mid = min(k + chunk // 2, len(t_sw) - 1)
                    view = model.chunk_view(static, occ, refl, sxy[mid], float(syaw[mid]))
                ts_us = plan.start_us + round(t * 1e6)
                boxes = traffic.boxes(float(t))
                if _in_window(cfg.scenario.empty_windows, float(t), plan.index):
                    pts = np.zeros(0, dtype=RADAR_DTYPE)
                    labels = np.zeros(0, dtype=LABEL_DTYPE)
                else:
                    sw = SweepWorld(*view, boxes)
                    pts, labels = model.sweep(
                        sw, sxy[k], float(syaw[k]), v_s[k], rng, return_labels=True
                    )
                label_parts.append(labels)
                is_key = k in key_of
                # Non-key sweeps point to the sample nearest in time (as nuScenes does).
                i_smp = key_of[k] if is_key else int(np.argmin(np.abs(t_smp - t)))
                sample_tok = smp_tok[i_smp]
                folder = "samples" if is_key else "sweeps"
                rel = f"{folder}/{ch}/{plan.name}__{ch}__{ts_us}.pcd"
                pad = int(
                    pad_rng.integers(cfg.output.padding_bytes[0], cfg.output.padding_bytes[1] + 1)
                )
                data = pcd_bytes(pts, padding=pad)
                # No per-file rename: the tables are written last, so an interrupted run is
                # detected by their absence (see is_complete).
                (root / rel).write_bytes(data)
                n_bytes += len(data)
                n_points += len(pts)
                ep_tok = make_token(seed, "ego_pose", plan.index, j, ch, k)
                records["ego_pose"].append(pose_record(ep_tok, ts_us, ego.xy[k], ego.yaw[k]))
                records["sample_data"].append(
                    {
                        "token": sd_tok[k],
                        "sample_token": sample_tok,
                        "ego_pose_token": ep_tok,
                        "calibrated_sensor_token": cs_token[ch],
                        "timestamp": ts_us,
                        "fileformat": "pcd",
                        "is_key_frame": bool(is_key),
                        "height": 0,
                        "width": 0,
                        "filename": rel,
                        "prev": sd_tok[k - 1] if k > 0 else "",
                        "next": sd_tok[k + 1] if k + 1 < len(t_sw) else "",
                    }
                )
                side["token"].append(sd_tok[k])
                side["timestamp_us"].append(ts_us)
                side["channel"].append(ch)
                side["v_sensor"].append(v_s[k])
                side["ego_speed"].append(ego.v_fwd_mps[k])
                side["yaw_rate"].append(ego.yaw_rate_radps[k])
                side["n_points"].append(len(pts))
    labels_all = np.concatenate(label_parts) if label_parts else np.zeros(0, LABEL_DTYPE)
    # Per-log ground truth for tests and evaluation (the reader never needs it).
    gt_t = np.arange(0.0, t_end, 0.05)
    ego = ego_fn(gt_t)
    out = root / "synthetic" / "logs"
    out.mkdir(parents=True, exist_ok=True)
    tmp = out / f".{plan.name}.tmp.npz"
    np.savez_compressed(
        tmp,
        sample_data_token=np.array(side["token"]),
        timestamp_us=np.array(side["timestamp_us"]),
        channel=np.array(side["channel"]),
        v_sensor=np.array(side["v_sensor"]).reshape(-1, 2),
        ego_speed_mps=np.array(side["ego_speed"]),
        yaw_rate_radps=np.array(side["yaw_rate"]),
        n_points=np.array(side["n_points"]),
        # Per-point truth, concatenated in sample_data order (offsets = cumsum of n_points).
        point_class=labels_all["cls"],
        point_kind=labels_all["kind"],
        point_ground_speed_mps=labels_all["ground_speed_mps"],
        gt_time_us=plan.start_us + np.round(gt_t * 1e6).astype(np.int64),
        gt_xy=ego.xy,
        gt_yaw=ego.yaw,
        gt_speed_mps=ego.v_fwd_mps,
        gt_yaw_rate_radps=ego.yaw_rate_radps,
        parked_xy=parked.xy,
        parked_yaw=parked.yaw,
        parked_length=parked.length,
        parked_width=parked.width,
        parked_id=parked.obj_id,
    )
    os.replace(tmp, out / f"{plan.name}.npz")
    log_rec = {
        "token": plan.token,
        "logfile": plan.name,
        "vehicle": cfg.output.vehicle,
        "date_captured": plan.date,
        "location": cfg.output.location,
    }
    stats = {
        "log": plan.name,
        "date": plan.date,
        "day": plan.day,
        "route": plan.route_index,
        "reversed": plan.reversed,
        "scenes": len(plan.scene_windows),
        "sweeps": len(records["sample_data"]),
        "points": n_points,
        "bytes": n_bytes,
        "samples": len(records["sample"]),
    }
    return {"log": log_rec, "calibrated_sensor": cs_records, **records, "stats": stats}


def _run_log(args):
    cfg_json, plan, dataroot = args
    cfg = SimConfig.model_validate_json(cfg_json)
    return simulate_log(cfg, plan, dataroot)


# --- top level ---------------------------------------------------------------------------------
def simulate(
    config_or_preset: SimConfig | str | Path,
    out_dir: str | Path,
    seed: int | None = None,
    progress: bool = True,
    overrides: list[str] | None = None,
    jobs: int | None = None,
    overwrite: bool = False,
    trajectory_tum: str | Path | None = None,
) -> SimulationSummary:
    """Generate a nuScenes-layout dataroot in ``out_dir``; deterministic for a seed."""
    t_start = time.perf_counter()
    if isinstance(config_or_preset, SimConfig):
        cfg = config_or_preset
        if overrides:
            from radarslam.config import apply_overrides, build_config

            cfg = build_config(SimConfig, apply_overrides(cfg.model_dump(mode="json"), overrides))
    else:
        cfg = load_sim_config(config_or_preset, overrides)
    upd = {}
    if seed is not None:
        upd["seed"] = int(seed)
    if jobs is not None:
        upd["jobs"] = int(jobs)
    if upd:  # validated like the config's own values (a negative seed is refused)
        from radarslam.config import build_config

        cfg = build_config(SimConfig, {**cfg.model_dump(), **upd}, source="simulate arguments")
    if trajectory_tum is not None:
        cfg = cfg.model_copy(
            update={"ego": cfg.ego.model_copy(update={"trajectory_tum": str(trajectory_tum)})}
        )
    for w in cfg.scenario.missing_radar:
        if w.channel not in CHANNELS:
            raise ConfigError(
                f"scenario.missing_radar: unknown channel {w.channel!r} "
                f"(one of {', '.join(CHANNELS)})"
            )
    world, tum = _cached_world(cfg)
    duration = None
    if tum is not None:
        duration = float(tum[-1, 0] - tum[0, 0])
        if duration < 3.0:
            raise ConfigError(
                f"{cfg.ego.trajectory_tum}: trajectory lasts {duration:.1f} s; need >= 3 s"
            )
    plans = plan_logs(cfg, duration)
    root = Path(out_dir)
    version = cfg.output.version
    if root.exists() and not root.is_dir():
        raise ConfigError(f"{root}: output path exists and is not a directory")
    existing = [
        p for p in (version, "samples", "sweeps", "synthetic", "maps") if (root / p).exists()
    ]
    if existing:
        if not overwrite:
            raise ConfigError(
                f"{root}: already holds a dataroot ({', '.join(existing)}); "
                "pass --overwrite to replace it"
            )
        for p in existing:  # tables first, so an interrupted overwrite is detectable
            shutil.rmtree(root / p)
    for ch in CHANNELS:
        (root / "samples" / ch).mkdir(parents=True, exist_ok=True)
        (root / "sweeps" / ch).mkdir(parents=True, exist_ok=True)

    results = _run_all(cfg, plans, root, progress)

    tables: dict[str, list] = {t: [] for t in TABLES}
    tables.update(static_tables(cfg.seed, CHANNELS))
    for res in results:
        tables["log"].append(res["log"])
        for name in ("calibrated_sensor", "scene", "sample", "sample_data", "ego_pose"):
            tables[name].extend(res[name])
    map_tok = make_token(cfg.seed, "map", 0)
    img = drivable_mask(world, cfg.city.map_resolution_m)
    fname = write_map(root, map_tok, img)
    tables["map"] = [
        {
            "token": map_tok,
            "log_tokens": [p.token for p in plans],
            "category": "semantic_prior",
            "filename": fname,
        }
    ]
    # Sidecar: the world model (ground truth for tests; the reader never needs it).
    syn = root / "synthetic"
    syn.mkdir(parents=True, exist_ok=True)
    write_text_atomic(syn / "config.yaml", dump_config(cfg))
    sc = world.scatterers
    tmp = syn / ".world.tmp.npz"
    np.savez_compressed(
        tmp,
        scatterer_xy=sc.xy,
        scatterer_class=sc.cls,
        scatterer_rcs_dbsm=sc.rcs_dbsm,
        occluders=world.occluders,
        reflectors=world.reflectors,
        nodes=world.network.nodes,
        edges=world.network.edges,
        parking_xy=world.parking.xy,
        map_resolution_m=cfg.city.map_resolution_m,
    )
    os.replace(tmp, syn / "world.npz")
    (root / version).mkdir(parents=True, exist_ok=True)
    for name in TABLES:
        path = root / version / f"{name}.json"
        write_json_atomic(path, tables[name], indent=None)
        os.chmod(path, 0o644)  # readable like the radar files (the temp file was 0600)
    stats = [r["stats"] for r in results]
    summary = SimulationSummary(
        dataroot=str(root),
        version=version,
        preset=cfg.name,
        seed=cfg.seed,
        n_logs=len(plans),
        n_days=len({p.day for p in plans}),
        n_scenes=len(tables["scene"]),
        n_samples=len(tables["sample"]),
        n_sweeps=len(tables["sample_data"]),
        n_points=sum(s["points"] for s in stats),
        bytes_written=_du(root),
        seconds=time.perf_counter() - t_start,
        per_log=stats,
    )
    write_json_atomic(syn / "summary.json", asdict(summary))
    return summary


def _du(root: Path) -> int:
    total = 0
    for dirpath, _, files in os.walk(root):
        for f in files:
            total += os.path.getsize(os.path.join(dirpath, f))
    return total


def _run_all(cfg: SimConfig, plans: list[LogPlan], root: Path, progress: bool) -> list[dict]:
    from tqdm import tqdm

    jobs = min(cfg.jobs, len(plans))
    bar = tqdm(total=len(plans), desc=f"simulate {cfg.name}", unit="log", disable=not progress)
    results: list[dict] = []
    try:
        if jobs <= 1:
            for p in plans:
                results.append(simulate_log(cfg, p, str(root)))
                bar.update(1)
        else:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            ctx = mp.get_context("fork") if "fork" in mp.get_all_start_methods() else None
            args = [(cfg.model_dump_json(), p, str(root)) for p in plans]
            with ProcessPoolExecutor(jobs, mp_context=ctx) as ex:
                for res in ex.map(_run_log, args):
                    results.append(res)
                    bar.update(1)
    finally:
        bar.close()
    return results
