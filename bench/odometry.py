"""Odometry benchmark on synthetic nuScenes-layout data: ours vs Doppler dead reckoning vs plain
kiss-icp, on a subset of the ``city`` preset and on one long multi-scene drive.

    python bench/odometry.py [--work /tmp/radarslam_bench_odometry] [--logs 2] [--scenes-per-log 3]
                             [--long-scenes 8] [--jobs 2] [--json results.json]

Datasets are generated once into ``--work`` (the simulator is deterministic) and reused.

* ``city``: ``--logs`` logs x ``--scenes-per-log`` scenes of 20 s from the city preset; scenes are
  separated by 1-8 s gaps, so each scene is its own odometry segment.
* ``long``: one log of ``--long-scenes`` consecutive scenes with 0.2-0.4 s gaps; the odometry runs
  through the gaps (``fusion.max_gap_s`` = 1 s) as one continuous drive.

Methods, all fed the same frames through the same reader (filters: invalid_state 0, ambig_state 3):

* ``doppler``: Doppler dead reckoning (joint multi-radar fit, trapezoid integration).
* ``kiss-icp``: kiss-icp's own ``KissICP`` pipeline (constant-velocity model, adaptive threshold,
  voxel 1 m, max range 100 m, deskew off), fed the same points ours registers: Doppler inliers of
  all radars in the ego frame, de-skewed with the Doppler twist, z = 0.
* ``ours``: Doppler-seeded kiss-icp registration fused with the Doppler motion (error-state KF).

Metrics (radarslam.eval.metrics, per continuous segment, pooled): ATE = SE(2)-aligned RMSE; RPE
translation RMSE over 1 s and over 10 m; KITTI drift = mean translation error over all 100 m
sub-segments in % (length-weighted over segments). Throughput: CPU time per frame of each method
(process time, excluding reading; libraries are imported before the workers fork, so one-time
imports are not counted), and frames per second of ours on ``--jobs`` cores from its CPU time per
frame plus reading; real time is 13 Hz.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import multiprocessing as mp
import os
import time
from pathlib import Path

import numpy as np

METHODS = ("doppler", "kiss-icp", "ours")
RADAR_HZ = 13.0


def generate(work: Path, args) -> dict[str, Path]:
    from radarslam.sim import simulate

    sets = {
        "city": [
            f"schedule.n_logs={args.logs}",
            f"schedule.scenes_per_log={args.scenes_per_log}",
            "jobs=1",
        ],
        "long": [
            "schedule.n_logs=1",
            f"schedule.scenes_per_log={args.long_scenes}",
            "schedule.scene_gap_s=[0.2, 0.4]",
            "schedule.route_length_m=4000.0",
            "seed=2019",
            "jobs=1",
        ],
    }
    out = {}
    for name, overrides in sets.items():
        digest = hashlib.md5("|".join(overrides).encode()).hexdigest()[:8]
        root = work / f"{name}_{digest}"
        if not (root / "v1.0-trainval" / "scene.json").is_file():
            t = time.perf_counter()
            print(f"generating {name} ({' '.join(overrides)}) -> {root}", flush=True)
            simulate("city", root, progress=False, overrides=overrides, overwrite=True)
            print(f"  {time.perf_counter() - t:.0f} s", flush=True)
        out[name] = root
    return out


def segments(dataroot: Path, max_gap_s: float) -> list[list[str]]:
    """Scene names grouped into continuous segments (consecutive scenes with small gaps)."""
    from radarslam.nuscenes.reader import NuScenesRadar

    reader = NuScenesRadar(dataroot, "v1.0-trainval")
    groups: list[list[str]] = []
    last_end = None
    last_log = None
    for s in reader.scenes():
        times = [f.timestamp_us for f in reader.iter_frames(s, key_frames_only=True)]
        start, end = times[0], times[-1]
        if groups and s.log_token == last_log and start - last_end < (max_gap_s + 0.6) * 1e6:
            groups[-1].append(s.name)
        else:
            groups.append([s.name])
        last_end, last_log = end, s.log_token
    return groups


def run_segment(job: tuple[str, list[str]]) -> dict:
    """All methods over one segment (worker process): poses, ground truth, CPU ms per frame."""
    from radarslam.nuscenes.filters import RadarPointFilter
    from radarslam.nuscenes.reader import NuScenesRadar
    from radarslam.odometry.baselines import make_odometry
    from radarslam.odometry.config import OdometryConfig

    dataroot, scenes = job
    cfg = OdometryConfig()
    pc = cfg.points
    reader = NuScenesRadar(dataroot, "v1.0-trainval")
    filters = RadarPointFilter(pc.invalid_states, pc.dynprop_states, pc.ambig_states)
    t_wall = time.perf_counter()
    t_cpu = time.process_time()
    frames = [f for s in scenes for f in reader.iter_frames(s, filters=filters)]
    read_cpu = time.process_time() - t_cpu
    out = {
        "scenes": scenes,
        "t": np.array([f.timestamp_us for f in frames]),
        "gt": np.array([f.world_from_ego for f in frames]),
    }
    out["read_cpu_ms"] = read_cpu / len(frames) * 1e3
    gaps = np.diff(out["t"]) * 1e-6
    assert gaps.max() < cfg.fusion.max_gap_s, f"segment {scenes} has a {gaps.max():.2f} s gap"
    for method in METHODS:
        odo = make_odometry(method, cfg)
        t0 = time.process_time()
        res = [odo.process(f) for f in frames]
        out[method] = np.array([r.world_from_ego for r in res])
        out[method + "_cpu_ms"] = (time.process_time() - t0) / len(frames) * 1e3
        if method == "ours":
            out["ours_accepted"] = float(np.mean([r.icp_accepted for r in res]))
    out["wall_s"] = time.perf_counter() - t_wall
    return out


def metrics_table(results: list[dict]) -> dict[str, dict]:
    from radarslam.eval import metrics as m

    table = {}
    for method in METHODS:
        ate_sq, ate_n, rpe1, rpe10, dr, dr_w, length = [], [], [], [], [], [], 0.0
        for r in results:
            est, gt, t = r[method], r["gt"], r["t"]
            seg_len = float(m.path_lengths_m(m.to_xy_yaw(gt))[-1])
            length += seg_len
            a = m.ate(est, gt, align="se2")
            ate_sq.append(a.rmse_m**2 * a.count)
            ate_n.append(a.count)
            rpe1.append(m.rpe(est, gt, t, 1.0, "s").trans_errors_m)
            rpe10.append(m.rpe(est, gt, None, 10.0, "m").trans_errors_m)
            d = m.drift(est, gt, (100.0,))
            if d.num_segments:
                dr.append(d.translation_pct)
                dr_w.append(seg_len)
        e1, e10 = np.concatenate(rpe1), np.concatenate(rpe10)
        table[method] = {
            "ate_m": float(np.sqrt(np.sum(ate_sq) / np.sum(ate_n))),
            "rpe_1s_m": float(np.sqrt(np.mean(e1**2))) if e1.size else float("nan"),
            "rpe_10m_m": float(np.sqrt(np.mean(e10**2))) if e10.size else float("nan"),
            "drift_pct": float(np.average(dr, weights=dr_w)) if dr else float("nan"),
            "cpu_ms_per_frame": _frame_average(results, method + "_cpu_ms"),
            "length_m": length,
        }
    return table


def _frame_average(results: list[dict], key: str) -> float:
    return float(np.average([r[key] for r in results], weights=[len(r["t"]) for r in results]))


def print_table(name: str, table: dict, frames: int, duration_s: float) -> None:
    print(f"\n{name}: {frames} frames, {duration_s:.0f} s, {table['ours']['length_m']:.0f} m")
    head = ("method", "ATE m", "RPE 1s m", "RPE 10m m", "drift %", "CPU ms/fr")
    print(f"{head[0]:<10} {head[1]:>8} {head[2]:>9} {head[3]:>10} {head[4]:>8} {head[5]:>10}")
    for method in METHODS:
        r = table[method]
        print(
            f"{method:<10} {r['ate_m']:>8.3f} {r['rpe_1s_m']:>9.3f} {r['rpe_10m_m']:>10.3f} "
            f"{r['drift_pct']:>8.3f} {r['cpu_ms_per_frame']:>10.2f}"
        )
    best = min(table["doppler"]["drift_pct"], table["kiss-icp"]["drift_pct"])
    ours = table["ours"]["drift_pct"]
    print(
        f"ours drift {ours:.3f} % (target <= 1.0 %): {'PASS' if ours <= 1.0 else 'FAIL'}; "
        f"ratio to the better baseline {ours / best:.2f} (target <= 0.5): "
        f"{'PASS' if ours <= 0.5 * best else 'FAIL'}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--work", type=Path, default=Path("/tmp/radarslam_bench_odometry"))
    ap.add_argument("--logs", type=int, default=2)
    ap.add_argument("--scenes-per-log", type=int, default=3)
    ap.add_argument("--long-scenes", type=int, default=8)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()

    args.work.mkdir(parents=True, exist_ok=True)
    roots = generate(args.work, args)
    # Import what the methods use before forking the workers, so that a one-time import (~0.5 s of
    # scipy.spatial and kiss-icp per worker) is not charged to the first segment's CPU per frame.
    import kiss_icp.kiss_icp  # noqa: F401
    import scipy.spatial  # noqa: F401

    import radarslam.odometry.baselines  # noqa: F401

    summary = {}
    for name, root in roots.items():
        jobs = [(str(root), seg) for seg in segments(root, 1.0)]
        t = time.perf_counter()
        with mp.get_context("fork").Pool(args.jobs) as pool:
            results = pool.map(run_segment, jobs, chunksize=1)
        wall = time.perf_counter() - t
        frames = sum(len(r["t"]) for r in results)
        duration = sum((r["t"][-1] - r["t"][0]) * 1e-6 for r in results)
        table = metrics_table(results)
        print_table(name, table, frames, duration)
        # Throughput of ours alone on `jobs` cores: its CPU per frame plus reading, per core.
        per_frame_ms = table["ours"]["cpu_ms_per_frame"] + _frame_average(results, "read_cpu_ms")
        fps = args.jobs * 1e3 / per_frame_ms
        print(
            f"throughput of ours with reading: {per_frame_ms:.2f} CPU ms/frame -> "
            f"{fps:.0f} frames/s on {args.jobs} cores = {fps / RADAR_HZ:.1f}x real time (13 Hz); "
            f"ICP accepted on {100 * _frame_average(results, 'ours_accepted'):.1f} % of frames; "
            f"bench wall {wall:.0f} s for 3 methods, load avg {os.getloadavg()[0]:.1f}"
        )
        summary[name] = {
            "frames": frames,
            "duration_s": duration,
            "segments": len(results),
            "methods": table,
            "ours_cpu_ms_per_frame_with_reading": per_frame_ms,
            "ours_realtime_factor": fps / RADAR_HZ,
        }
    if args.json:
        args.json.write_text(json.dumps(summary, indent=2) + "\n")


if __name__ == "__main__":
    main()
