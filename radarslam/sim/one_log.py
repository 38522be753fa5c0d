"""Simulating one log: its traffic and ego drive, each radar's sweeps written as ``.pcd`` files,
and the log's table records and sidecar returned to the driver."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from radarslam.nuscenes.pcd import pcd_bytes
from radarslam.sim.config import SimConfig
from radarslam.sim.ego import TumEgo, canonical_routes, extend_route
from radarslam.sim.planning import LogPlan, _cached_world
from radarslam.sim.radar import (
    LABEL_DTYPE,
    NUSCENES_MOUNTS,
    RadarModel,
    SweepWorld,
    box_scatterers,
    clock_offset_s,
    mounting_errors,
)
from radarslam.sim.traffic import EGO_START_S, EgoMotion, path_traffic, simulate_traffic
from radarslam.sim.world import Boxes, Scatterers, StaticWorld, parked_cars
from radarslam.sim.writer import calibrated_sensor_record, make_token, pose_record
from radarslam.types import RADAR_DTYPE


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
    own_street = None  # cars on a given trajectory's own street
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
        if cfg.traffic.along_trajectory:
            own_street = path_traffic(
                ego_fn,
                ego_src.duration_s,
                cfg.traffic,
                np.random.default_rng([seed, 909, plan.index]),
                t_end,
            )
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
    models = {m.channel: RadarModel(cfg.radar, m.channel) for m in mounts}
    errors = mounting_errors(cfg.radar, seed)
    clock_s = clock_offset_s(cfg.radar, seed, plan.index)

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
            t_key = t_sw + errors[ch].timestamp_offset_s + clock_s
            for i, tsmp in enumerate(t_smp):
                nearest = int(np.argmin(np.abs(t_key - tsmp)))
                if abs(t_key[nearest] - tsmp) <= 0.6 * cfg.radar.period_s:
                    key_of[nearest] = i
            # As in nuScenes, a radar's chain in a scene starts with its first key frame.
            if key_of:
                start = min(key_of)
                t_sw = t_sw[start:]
                key_of = {k - start: i for k, i in key_of.items()}
            # The unit measures at t_sw with its true (perturbed) mounting; the dataset records
            # the nominal mounting and a timestamp shifted by the unit's and the log's offsets.
            err = errors[ch]
            true_yaw = np.deg2rad(m.yaw_deg + err.yaw_deg)
            sxy, syaw, v_s = _sensor_states(ego_fn(t_sw), (m.x_m, m.y_m), true_yaw)
            t_written = t_sw + err.timestamp_offset_s + clock_s
            ego = ego_fn(t_written)
            model = models[ch]
            sd_tok = [
                make_token(seed, "sample_data", plan.index, j, ch, k) for k in range(len(t_sw))
            ]
            chunk = 13  # ~1 s of sweeps share one pre-culled view of the static world
            for k, t in enumerate(t_sw):
                if k % chunk == 0:
                    mid = min(k + chunk // 2, len(t_sw) - 1)
                    view = model.chunk_view(static, occ, refl, sxy[mid], float(syaw[mid]))
                ts_us = plan.start_us + round(t_written[k] * 1e6)
                boxes = traffic.boxes(float(t))
                if own_street is not None:
                    boxes = Boxes.concat([boxes, own_street.boxes(float(t))])
                dropped = rng.uniform() < cfg.radar.empty_sweep_probability
                if dropped or _in_window(cfg.scenario.empty_windows, float(t), plan.index):
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
                i_smp = key_of[k] if is_key else int(np.argmin(np.abs(t_smp - t_written[k])))
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
        "clock_offset_s": clock_s,
    }
    return {"log": log_rec, "calibrated_sensor": cs_records, **records, "stats": stats}


def _run_log(args):
    cfg_json, plan, dataroot = args
    cfg = SimConfig.model_validate_json(cfg_json)
    return simulate_log(cfg, plan, dataroot)
