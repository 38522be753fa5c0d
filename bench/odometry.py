"""Odometry benchmark: ours vs Doppler dead reckoning vs the kiss-icp peer, on real radar first.

    python bench/odometry.py              # the real split, ../shared/data/nuscenes-mini-radar
    python bench/odometry.py --dataroot D --version v1.0-trainval [--scenes a,b]
    python bench/odometry.py --synthetic  # the synthetic city subset and long drive
    python bench/odometry.py ... --json results.json

Each scene is its own odometry segment, started on its first ground-truth pose. All methods read
the same frames (filters invalid_state 0, ambig_state 3):

* ``doppler``: Doppler dead reckoning (the joint five-radar fit, trapezoid integration,
  zero-velocity updates), no registration.
* ``kiss-icp`` (the peer): kiss-icp's own ``KissICP`` pipeline, one frame of all five radars in the
  ego frame, z = 0, moving points dropped by the Doppler fit and the sweeps de-skewed to the
  frame's time with the Doppler twist; voxel 1 m, max range 100 m, kiss-icp's deskew off, its
  defaults otherwise.
* ``ours``: Doppler-seeded kiss-icp registration fused with the Doppler motion
  (radarslam/configs/odometry).

Per scene and pooled over scenes (ATE and RPE as RMS over all poses or pairs, drift weighted by
length): ATE after SE(2) alignment and from the first pose, RPE translation over 1 s and 10 m,
end-point drift (end position error from the first pose, % of the path), CPU ms per frame.
Then the ATE split along and across the ground truth's heading, each method's scale (a
similarity alignment: ground-truth length over the estimate's; none for a scene that drives less
than 10 m, as ``radarslam eval``'s ``scale_min_path_m``) and the ground truth's clock
offset that fits best. Then the Doppler fit's heading over each scene against the ground truth,
the key-frame NEES of ours (mean over key-frame motions; 3 is consistent) and ours' real-time
factor on ``--jobs`` cores (CPU per frame with the sweeps' reading, and the tables' loading once
per process; 13 Hz radar), and the start-up a process pays before its first frame (imports and
compiled kernels, about 1.5 s) apart, with the factor it leaves spread over the split. Where
every scene is its own segment, ours also runs over all of them in one run, in order and
reversed, as ``radarslam odometry`` over a dataroot does: each car's Doppler calibration then
carries over to its next scenes.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import multiprocessing as mp
import sys
import time
from pathlib import Path

import numpy as np

METHODS = ("doppler", "kiss-icp", "ours")
RADAR_HZ = 13.0
REAL_DATAROOT = (
    Path(__file__).resolve().parents[1].parent / "shared" / "data" / "nuscenes-mini-radar"
)

#: Targets on the real split (pooled unless said otherwise).
ATE_RATIO_TARGET = 0.6
RPE10_RATIO_TARGET = 0.8
HEADING_RATE_TARGET_DEG_S = 0.3
# The ground truth's clock is searched this far either way for the offset that fits best.
CLOCK_OFFSET_MAX_S = 0.1
NEES_RANGE = (1.5, 6.0)  # 0.5-2x the dimension (3)
REALTIME_TARGET = 20.0


def synthetic_dataroots(work: Path) -> dict[str, Path]:
    """The synthetic city subset (6 scenes of 20 s) and one long drive of 8 chained scenes,
    generated once into ``work`` per resolved simulator config (the simulator is
    deterministic)."""
    from radarslam.sim import simulate
    from radarslam.sim.config import load_sim_config

    sets = {
        "city": ["schedule.n_logs=2", "schedule.scenes_per_log=3", "jobs=1"],
        "long": [
            "schedule.n_logs=1",
            "schedule.scenes_per_log=8",
            "schedule.scene_gap_s=[0.2, 0.4]",
            "schedule.route_length_m=4000.0",
            "seed=2019",
            "jobs=1",
        ],
    }
    out = {}
    for name, overrides in sets.items():
        # The resolved config, defaults included: a changed simulator default is a new world.
        resolved = load_sim_config("city", overrides).model_dump_json()
        digest = hashlib.md5(resolved.encode()).hexdigest()[:8]
        root = work / f"{name}_{digest}"
        if not (root / "v1.0-trainval" / "scene.json").is_file():
            print(f"generating {name} ({' '.join(overrides)}) -> {root}", flush=True)
            simulate("city", root, progress=False, overrides=overrides, overwrite=True)
        out[name] = root
    return out


def segments(reader, scenes: list[str], chain: bool, max_gap_s: float) -> list[list[str]]:
    """Scenes grouped into odometry segments: one per scene, or (``chain``) consecutive scenes of
    one log whose frames follow within ``max_gap_s``."""
    if not chain:
        return [[s] for s in scenes]
    groups: list[list[str]] = []
    last_end = last_log = None
    for name in scenes:
        info = reader.scene(name)
        times = [f.timestamp_us for f in reader.iter_frames(name, key_frames_only=True)]
        if groups and info.log_token == last_log and times[0] - last_end < (max_gap_s + 0.6) * 1e6:
            groups[-1].append(name)
        else:
            groups.append([name])
        last_end, last_log = times[-1], info.log_token
    return groups


def odometry_config(overrides: list[str]):
    """The shipped odometry config (radarslam/configs/odometry/default.yaml, as `radarslam
    odometry` reads it) with ``--set`` overrides; ConfigError names a bad one."""
    from radarslam.config import CONFIG_DIR, load_config
    from radarslam.odometry.config import OdometryConfig

    return load_config(OdometryConfig, CONFIG_DIR / "odometry" / "default.yaml", overrides)


def run_segment(job: tuple[str, str, list[str], list[str]]) -> dict:
    """Every method over one segment (a worker process): poses, ground truth, key-frame motions of
    ours, CPU ms per frame."""
    from radarslam.nuscenes.filters import RadarPointFilter
    from radarslam.nuscenes.reader import NuScenesRadar
    from radarslam.odometry.baselines import make_odometry
    from radarslam.odometry.run import second_pass, single_pass, total_calibration

    dataroot, version, scenes, overrides = job
    cfg = odometry_config(overrides)
    pc = cfg.points
    reader = NuScenesRadar(dataroot, version)
    filters = RadarPointFilter(pc.invalid_states, pc.dynprop_states, pc.ambig_states)
    # The tables load once per run, however many scenes it covers (a worker here runs one
    # scene): timed apart from the reading of the sweeps, and counted once per run below.
    t_cpu = time.process_time()
    reader.tables.radar  # noqa: B018 (the property loads them)
    load_cpu = time.process_time() - t_cpu
    t_cpu = time.process_time()
    frames = [f for s in scenes for f in reader.iter_frames(s, filters=filters)]
    read_cpu = time.process_time() - t_cpu
    out: dict = {
        "scenes": scenes,
        "t": np.array([f.timestamp_us for f in frames]),
        "gt": np.array([f.world_from_ego for f in frames]),
        "read_cpu_ms": read_cpu / len(frames) * 1e3,
        "load_cpu_s": load_cpu,
    }
    cal = cfg.fusion.calibration
    for method in METHODS:
        run_cfg = cfg
        t0 = time.process_time()
        if method == "ours" and cal.passes > 1 and cal.yaw_bias_model == "mounting":
            first = make_odometry(method, single_pass(cfg, dict(cfg.mounting_yaw_deg)))
            for f in frames[:: cal.pass_frame_stride]:
                first.process(f)
            run_cfg = second_pass(cfg, first.calibration.as_dict())
        odo = make_odometry(method, run_cfg)
        res = [odo.process(f) for f in frames]
        out[method + "_cpu_ms"] = (time.process_time() - t0) / len(frames) * 1e3
        out[method] = np.array([r.world_from_ego for r in res])
        if method == "doppler":
            out["doppler_yaw_rate"] = np.array(
                [r.doppler.yaw_rate_radps if r.doppler.valid else np.nan for r in res]
            )
        if method == "ours":
            out["calibration"] = odo.calibration.as_dict()
            if run_cfg is not cfg:
                out["calibration"] = total_calibration(run_cfg, out["calibration"])
            mounting = out["calibration"].get("mounting_yaw_error_deg")
            if mounting:
                # The Doppler fit again, with the mounting yaws ours estimated on this segment.
                recal = cfg.model_copy(update={"mounting_yaw_deg": mounting})
                dr = make_odometry("doppler", recal)
                out["doppler_calibrated"] = np.array([dr.process(f).world_from_ego for f in frames])
            kf = [i for i, r in enumerate(res) if r.key_frame_motion is not None]
            out["kf_index"] = np.array(kf, dtype=int)
            out["kf_motion"] = np.array([res[i].key_frame_motion for i in kf]).reshape(-1, 4, 4)
            out["kf_cov"] = np.array([res[i].key_frame_covariance for i in kf]).reshape(-1, 3, 3)
            out["kf_all"] = np.flatnonzero([r.is_key_frame for r in res])
    return out


def _label(scenes: list[str]) -> str:
    return scenes[0] if len(scenes) == 1 else f"{scenes[0]}+{len(scenes) - 1}"


def _yaw(poses: np.ndarray) -> np.ndarray:
    from radarslam.geometry import yaws_of

    return np.unwrap(yaws_of(poses))


def segment_metrics(r: dict, method: str) -> dict:
    from radarslam.eval import metrics as m
    from radarslam.eval.evaluate import EvalConfig

    est, gt, t = r[method], r["gt"], r["t"]
    length = float(m.path_lengths_m(m.to_xy_yaw(gt))[-1])
    first = m.ate(est, gt, align="first")
    aligned = m.ate(est, gt, align="se2")
    scaled = m.ate(est, gt, align="sim2")
    clock = m.ate_clock_offsets(est, t, gt, t, CLOCK_OFFSET_MAX_S)
    e1 = _rpe_errors(est, gt, t, 1.0, "s")
    e10 = _rpe_errors(est, gt, None, 10.0, "m")
    return {
        "frames": len(t),
        "length_m": length,
        "duration_s": float((t[-1] - t[0]) * 1e-6),
        "ate_m": aligned.rmse_m,
        "ate_along_m": aligned.along_rmse_m,
        "ate_cross_m": aligned.cross_rmse_m,
        # ground-truth length / estimated length (Umeyama with scale): above 1, estimate short;
        # NaN on a drive too short for it to mean anything, as `radarslam eval` reports it
        "sim2_scale": (
            scaled.alignment.scale if length >= EvalConfig().scale_min_path_m else float("nan")
        ),
        "clock_offset_ms": 1e3 * clock.best_offset_s if clock else float("nan"),
        "ate_clock_m": clock.best_rmse_m if clock else float("nan"),
        # the offsets, the squared ATE at each and the poses compared, to pool a common offset
        "clock_offsets_sq": (clock.offsets_s, np.square(clock.rmse_m)) if clock else None,
        "clock_count": clock.count if clock else 0,
        "ate_first_m": first.rmse_m,
        # A scene that barely moves has no meaningful drift per distance.
        "end_drift_pct": 100.0 * float(first.errors_m[-1]) / length if length >= 1.0 else np.nan,
        "rpe_1s_sq": e1,
        "rpe_10m_sq": e10,
        "cpu_ms_per_frame": r[method + "_cpu_ms"],
    }


def _rpe_errors(est, gt, t, delta, unit) -> np.ndarray:
    """Squared translation errors of every RPE pair (pooled over segments by the caller)."""
    from radarslam.eval import metrics as m

    e, ref = m.to_xy_yaw(est), m.to_xy_yaw(gt)
    pairs = m.pairs_for_delta(ref, t, delta, unit)
    if not len(pairs):
        return np.zeros(0)
    err = m.relative_errors(e, ref, pairs)
    return np.sum(err[:, :2] ** 2, axis=1)


def pooled(rows: list[dict]) -> dict:
    frames = np.array([x["frames"] for x in rows], dtype=float)
    lengths = np.array([x["length_m"] for x in rows])
    e1 = np.concatenate([x["rpe_1s_sq"] for x in rows])
    e10 = np.concatenate([x["rpe_10m_sq"] for x in rows])
    return {
        "frames": int(frames.sum()),
        "length_m": float(lengths.sum()),
        "duration_s": float(sum(x["duration_s"] for x in rows)),
        "ate_m": float(
            np.sqrt(np.sum(frames * np.square([x["ate_m"] for x in rows])) / frames.sum())
        ),
        **{
            key: float(np.sqrt(np.sum(frames * np.square([x[key] for x in rows])) / frames.sum()))
            for key in ("ate_first_m", "ate_along_m", "ate_cross_m", "ate_clock_m")
        },
        "end_drift_pct": _nan_average([x["end_drift_pct"] for x in rows], lengths),
        "sim2_scale": _nan_average([x["sim2_scale"] for x in rows], lengths),
        **common_clock(rows),
        "rpe_1s_m": float(np.sqrt(np.mean(e1))) if e1.size else float("nan"),
        "rpe_10m_m": float(np.sqrt(np.mean(e10))) if e10.size else float("nan"),
        "cpu_ms_per_frame": float(
            np.average([x["cpu_ms_per_frame"] for x in rows], weights=frames)
        ),
    }


def common_clock(rows: list[dict]) -> dict[str, float]:
    """The one clock offset of the ground truth (ms) that fits every segment together best,
    and the pooled ATE there (m)."""
    found = [x for x in rows if x["clock_count"] > 0]
    offset_ms = ate_m = float("nan")
    if found:
        counts = np.array([x["clock_count"] for x in found], dtype=float)
        pooled_sq = counts @ np.array([x["clock_offsets_sq"][1] for x in found]) / counts.sum()
        k = int(np.argmin(pooled_sq))
        offset_ms = 1e3 * float(found[0]["clock_offsets_sq"][0][k])
        ate_m = float(np.sqrt(pooled_sq[k]))
    return {"clock_offset_common_ms": offset_ms, "ate_clock_common_m": ate_m}


def _nan_average(values, weights) -> float:
    v, w = np.asarray(values, dtype=float), np.asarray(weights, dtype=float)
    ok = np.isfinite(v)
    return float(np.average(v[ok], weights=w[ok])) if ok.any() else float("nan")


def _public(row: dict) -> dict:
    out = {k: v for k, v in row.items() if not k.endswith("_sq")}  # arrays, not JSON
    for key, sq in (("rpe_1s_m", "rpe_1s_sq"), ("rpe_10m_m", "rpe_10m_sq")):
        if sq in row:
            out[key] = float(np.sqrt(np.mean(row[sq]))) if row[sq].size else float("nan")
    return out


def heading_check(r: dict, key: str = "doppler") -> dict:
    """The Doppler fit's yaw rate integrated over the segment (zero-velocity updates included, as
    the dead reckoning does) against the ground truth's heading change."""
    yaw_dr = _yaw(r[key])
    yaw_gt = _yaw(r["gt"])
    duration = float((r["t"][-1] - r["t"][0]) * 1e-6)
    err = float(np.degrees((yaw_dr[-1] - yaw_dr[0]) - (yaw_gt[-1] - yaw_gt[0])))
    return {
        "doppler_heading_deg": float(np.degrees(yaw_dr[-1] - yaw_dr[0])),
        "gt_heading_deg": float(np.degrees(yaw_gt[-1] - yaw_gt[0])),
        "error_deg": err,
        "bound_deg": HEADING_RATE_TARGET_DEG_S * duration,
        "error_rate_deg_s": abs(err) / max(duration, 1e-9),
    }


def key_frame_nees(r: dict) -> np.ndarray:
    from radarslam.eval import metrics as m
    from radarslam.geometry import invert

    if not len(r["kf_index"]):
        return np.zeros(0)
    kf_all = list(r["kf_all"])
    gt = r["gt"]
    ref = []
    for i in r["kf_index"]:
        prev = kf_all[kf_all.index(i) - 1]
        ref.append(invert(gt[prev]) @ gt[i])
    return m.relative_motion_nees(r["kf_motion"], r["kf_cov"], np.array(ref))


def print_table(title: str, per_scene: dict[str, dict[str, dict]], pool: dict[str, dict]) -> None:
    print(f"\n{title}")
    head = (
        f"{'scene':<12} {'method':<9} {'frames':>6} {'len m':>6} {'ATE m':>7} {'ATE1 m':>7} "
        f"{'RPE1s m':>8} {'RPE10m m':>9} {'end %':>6} {'CPU ms':>7}"
    )
    print(head)
    print("-" * len(head))
    for scene, rows in [*per_scene.items(), ("pooled", pool)]:
        for method in METHODS:
            x = _public(rows[method])
            print(
                f"{scene:<12} {method:<9} {x['frames']:>6d} {x['length_m']:>6.0f} "
                f"{x['ate_m']:>7.3f} {x['ate_first_m']:>7.3f} {x['rpe_1s_m']:>8.3f} "
                f"{x['rpe_10m_m']:>9.3f} {x['end_drift_pct']:>6.2f} {x['cpu_ms_per_frame']:>7.2f}"
            )


def print_split(per_scene: dict[str, dict[str, dict]], pool: dict[str, dict]) -> None:
    """ATE along and across the ground truth's heading, the scale of a similarity alignment, and
    the ATE against the ground truth read with its clock shifted by the offset that fits each
    scene and method best (within +-100 ms)."""
    print(
        "\nATE split (m, SE(2)-aligned): along / across the ground truth's heading; the scale "
        "of a similarity alignment (ground truth / estimate, pooled weighted by length); the "
        "ground truth's clock shifted by the offset that fits best (ms, + = radar stamps early) "
        "and the ATE there"
    )
    head = (
        f"{'scene':<12} {'method':<9} {'along':>7} {'across':>7} {'scale':>7} {'offset':>7} "
        f"{'ATE':>7}"
    )
    print(head)
    print("-" * len(head))
    for scene, rows in [*per_scene.items(), ("pooled", pool)]:
        for method in METHODS:
            x = rows[method]
            off = x.get("clock_offset_ms", float("nan"))
            print(
                f"{scene:<12} {method:<9} {x['ate_along_m']:>7.3f} {x['ate_cross_m']:>7.3f} "
                f"{x['sim2_scale']:>7.4f} {'' if off != off else f'{off:.0f}':>7} "
                f"{x['ate_clock_m']:>7.3f}"
            )
    ours, peer = pool["ours"], pool["kiss-icp"]
    print(
        f"at each scene's best clock offset, pooled ATE ours {ours['ate_clock_m']:.3f} m = "
        f"{ours['ate_clock_m'] / peer['ate_clock_m']:.2f}x the peer's {peer['ate_clock_m']:.3f} "
        f"m; at one offset for the split, ours {ours['ate_clock_common_m']:.3f} m at "
        f"{ours['clock_offset_common_ms']:.0f} ms = "
        f"{ours['ate_clock_common_m'] / peer['ate_clock_common_m']:.2f}x the peer's "
        f"{peer['ate_clock_common_m']:.3f} m at {peer['clock_offset_common_ms']:.0f} ms"
    )


def verdicts(per_scene, pool, heading, nees, realtime, spread=None) -> list[str]:
    ours, peer = pool["ours"], pool["kiss-icp"]
    lines = []

    def say(ok: bool, text: str) -> None:
        lines.append(f"{'PASS' if ok else 'FAIL'}  {text}")

    say(
        ours["ate_m"] <= ATE_RATIO_TARGET * peer["ate_m"],
        f"pooled ATE ours {ours['ate_m']:.3f} m = {ours['ate_m'] / peer['ate_m']:.2f}x the peer "
        f"({peer['ate_m']:.3f} m; target <= {ATE_RATIO_TARGET}x)",
    )
    say(
        ours["rpe_10m_m"] <= RPE10_RATIO_TARGET * peer["rpe_10m_m"],
        f"pooled RPE 10 m ours {ours['rpe_10m_m']:.3f} m = "
        f"{ours['rpe_10m_m'] / peer['rpe_10m_m']:.2f}x the peer (target <= {RPE10_RATIO_TARGET}x)",
    )
    worse = [
        s for s, rows in per_scene.items() if rows["ours"]["ate_m"] > rows["kiss-icp"]["ate_m"]
    ]
    say(not worse, f"scenes where ours' ATE is worse than the peer's: {', '.join(worse) or 'none'}")
    bad = [s for s, h in heading.items() if abs(h["error_deg"]) > h["bound_deg"]]
    worst = max(heading.values(), key=lambda h: h["error_rate_deg_s"])
    say(
        not bad,
        f"Doppler heading within {HEADING_RATE_TARGET_DEG_S} deg/s x duration on every scene "
        f"(worst {worst['error_rate_deg_s']:.2f} deg/s; outside: {', '.join(bad) or 'none'})",
    )
    mean_nees = float(np.nanmean(nees)) if nees.size else float("nan")
    say(
        NEES_RANGE[0] <= mean_nees <= NEES_RANGE[1],
        f"key-frame NEES of ours {mean_nees:.2f} over {nees.size} motions (median "
        f"{np.nanmedian(nees) if nees.size else float('nan'):.2f}; target mean in "
        f"{NEES_RANGE[0]}-{NEES_RANGE[1]} for 3 dof)",
    )
    say(
        realtime >= REALTIME_TARGET,
        f"ours {realtime:.1f}x real time (target >= {REALTIME_TARGET}x)",
    )
    if spread is not None:
        rows = spread["scenes"]
        n = len(spread["seeds"])
        p_ours, p_peer = rows["pooled"]["ours"], rows["pooled"]["kiss-icp"]
        ratio = p_ours["median_m"] / p_peer["median_m"]
        say(
            ratio <= ATE_RATIO_TARGET,
            f"over {n} Doppler seeds: pooled ATE ours median {p_ours['median_m']:.3f} m = "
            f"{ratio:.2f}x the peer's median (worst {p_ours['worst_m']:.3f} against "
            f"{p_peer['worst_m']:.3f} m; target <= {ATE_RATIO_TARGET}x)",
        )
        worse = [
            f"{s} ({r['ours_worse_than_peer']} of {n})"
            for s, r in rows.items()
            if s != "pooled" and r["ours"]["median_m"] > r["kiss-icp"]["median_m"]
        ]
        say(
            not worse,
            "over the seeds: scenes where ours' median ATE is worse than the peer's: "
            + (", ".join(worse) or "none"),
        )
    return lines


def seed_spread(dataroot: Path, version: str, groups: list[list[str]], overrides: list[str],
                jobs: int, seeds: int, first: dict[str, dict[str, dict]]) -> dict:  # fmt: skip
    """ATE of every method and scene over ``seeds`` Doppler RANSAC seeds (the configured one,
    whose results are ``first``, and the next ``seeds - 1``): the moving-point rejection, the
    fit and everything downstream change with the seed, and a single seed can hide a scene that
    breaks away on another."""
    base = odometry_config(overrides).doppler.seed
    extra = [
        (str(dataroot), version, g, [*overrides, f"doppler.seed={base + k}"])
        for k in range(1, seeds)
        for g in groups
    ]
    with mp.get_context("fork").Pool(max(1, min(jobs, len(extra)))) as pool:
        results = pool.map(run_segment, extra, chunksize=1)
    runs = [first]
    for k in range(seeds - 1):
        part = results[k * len(groups) : (k + 1) * len(groups)]
        runs.append(
            {_label(r["scenes"]): {mm: segment_metrics(r, mm) for mm in METHODS} for r in part}
        )
    out: dict = {"seeds": list(range(base, base + seeds)), "scenes": {}}
    for scene in [*first, "pooled"]:
        per_method = {}
        for mm in METHODS:
            if scene == "pooled":
                ates = [pooled([rows[mm] for rows in run.values()])["ate_m"] for run in runs]
            else:
                ates = [run[scene][mm]["ate_m"] for run in runs]
            per_method[mm] = {
                "ate_m": ates,
                "median_m": float(np.median(ates)),
                "worst_m": float(np.max(ates)),
            }
        ours, peer = per_method["ours"]["ate_m"], per_method["kiss-icp"]["ate_m"]
        worse = sum(a > b for a, b in zip(ours, peer, strict=True))
        per_method["ours_worse_than_peer"] = int(worse)
        out["scenes"][scene] = per_method
    print(f"\nATE over {seeds} Doppler RANSAC seeds ({base}-{base + seeds - 1}), m: median / worst")
    cols = " ".join(f"{mm:>15}" for mm in METHODS)
    head = f"{'scene':<12} {cols}  ours worse than the peer"
    print(head)
    print("-" * len(head))
    for scene, row in out["scenes"].items():
        cells = " ".join(
            f"{row[mm]['median_m']:>7.3f} / {row[mm]['worst_m']:<5.3f}" for mm in METHODS
        )
        print(f"{scene:<12} {cells}  {row['ours_worse_than_peer']} of {seeds}")
    return out


def run_in_sequence(job: tuple[str, str, list[str], list[str]]) -> dict[str, float]:
    """Ours over all ``scenes`` in one run, in that order (a worker process): each scene's ATE
    (SE(2)-aligned) and frames. Each vehicle's Doppler calibration carries over from its earlier
    scenes (a rig is known by its nominal extrinsics)."""
    from radarslam.eval import metrics as m
    from radarslam.nuscenes.reader import NuScenesRadar
    from radarslam.odometry.run import run_odometry

    dataroot, version, scenes, overrides = job
    reader = NuScenesRadar(dataroot, version)
    traj = run_odometry(reader, scenes, odometry_config(overrides), progress=False)
    out = {}
    for name in scenes:
        sub = traj.scene(name)
        out[name] = (m.ate(sub.poses, sub.ground_truth, align="se2").rmse_m, len(sub))
    return out


def sequence_runs(dataroot: Path, version: str, names: list[str], overrides: list[str],
                  jobs: int, seeds: int, alone: dict[str, dict]) -> dict:  # fmt: skip
    """Ours over the whole split in one run, scenes in the dataset's order and reversed, over
    the Doppler seeds: what a user running every scene at once gets, against each scene alone."""
    base = odometry_config(overrides).doppler.seed
    orders = {"in order": names, "reversed": names[::-1]}
    work = [
        (str(dataroot), version, order, [*overrides, f"doppler.seed={base + k}"])
        for order in orders.values()
        for k in range(seeds)
    ]
    with mp.get_context("fork").Pool(max(1, min(jobs, len(work)))) as pool:
        results = pool.map(run_in_sequence, work, chunksize=1)
    out: dict = {}
    for i, label in enumerate(orders):
        runs = results[i * seeds : (i + 1) * seeds]
        per = {n: float(np.median([r[n][0] for r in runs])) for n in names}
        frames = np.array([runs[0][n][1] for n in names], dtype=float)
        pooled_runs = [
            np.sqrt(np.sum(frames * np.square([r[n][0] for n in names])) / frames.sum())
            for r in runs
        ]
        out[label] = {"scenes": per, "pooled_median_m": float(np.median(pooled_runs))}
    print(
        f"\nours over the whole split in one run (each car's calibration carried to its next "
        f"scenes), median ATE over {seeds} Doppler seed(s), m"
    )
    head = f"{'scene':<12} {'alone':>8} {'in order':>9} {'reversed':>9}"
    print(head)
    print("-" * len(head))
    for n in names:
        a = alone.get(n, float("nan"))
        print(f"{n:<12} {a:>8.3f} {out['in order']['scenes'][n]:>9.3f} "
              f"{out['reversed']['scenes'][n]:>9.3f}")  # fmt: skip
    print(
        f"{'pooled':<12} {alone.get('pooled', float('nan')):>8.3f} "
        f"{out['in order']['pooled_median_m']:>9.3f} {out['reversed']['pooled_median_m']:>9.3f}"
    )
    return out


def startup_cpu_s() -> float:
    """CPU seconds a fresh process spends before the odometry's first frame: the interpreter,
    the imports and the registration's compiled kernels (:func:`load_kernels`, numba's own
    start-up most of it), measured on a child process of its own."""
    import resource
    import subprocess

    code = (
        "import kiss_icp.kiss_icp, radarslam.odometry.baselines\n"
        "from radarslam.odometry import load_kernels\n"
        "load_kernels()\n"
    )
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    subprocess.run([sys.executable, "-c", code], check=True)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def evaluate(name: str, dataroot: Path, version: str, scenes: list[str] | None, chain: bool,
             jobs: int, overrides: list[str], seeds: int = 1,
             startup_s: float = 0.0) -> dict:  # fmt: skip
    from radarslam.nuscenes.reader import NuScenesRadar

    reader = NuScenesRadar(dataroot, version)
    names = scenes or [s.name for s in reader.scenes()]
    groups = segments(reader, names, chain, 1.0)
    jobs_list = [(str(dataroot), version, g, overrides) for g in groups]
    t = time.perf_counter()
    with mp.get_context("fork").Pool(max(1, min(jobs, len(jobs_list)))) as pool:
        results = pool.map(run_segment, jobs_list, chunksize=1)
    wall = time.perf_counter() - t
    per_scene = {
        _label(r["scenes"]): {mm: segment_metrics(r, mm) for mm in METHODS} for r in results
    }
    pool_rows = {mm: pooled([rows[mm] for rows in per_scene.values()]) for mm in METHODS}
    print_table(f"{name}: {dataroot} ({version})", per_scene, pool_rows)
    print_split(per_scene, pool_rows)
    raw_heading = {_label(r["scenes"]): heading_check(r) for r in results}
    calibrated = all("doppler_calibrated" in r for r in results)
    heading = (
        {_label(r["scenes"]): heading_check(r, "doppler_calibrated") for r in results}
        if calibrated
        else raw_heading
    )
    print(
        "\nDoppler heading over each scene (deg): ground truth, nominal calibration's fit and "
        "error"
        + (", fit and error with the mounting yaws ours estimated" if calibrated else "")
        + ", bound"
    )
    for s, h in heading.items():
        raw = raw_heading[s]
        cal = f" {h['doppler_heading_deg']:>8.1f} {h['error_deg']:>+7.1f}" if calibrated else ""
        print(
            f"  {s:<12} {h['gt_heading_deg']:>8.1f} {raw['doppler_heading_deg']:>8.1f} "
            f"{raw['error_deg']:>+7.1f}{cal} {h['bound_deg']:>6.1f}"
        )
    cals = {_label(r["scenes"]): r["calibration"] for r in results}
    print("\nDoppler calibration ours estimated per scene:")
    for s, c in cals.items():
        if "mounting_yaw_error_deg" in c:
            vals = " ".join(
                f"{ch.removeprefix('RADAR_')} {v:+.2f}+-{c['mounting_yaw_sigma_deg'][ch]:.2f}"
                for ch, v in c["mounting_yaw_error_deg"].items()
            )
            print(f"  {s:<12} mounting yaw deg: {vals}")
        else:
            print(f"  {s:<12} {c}")
    nees = np.concatenate([key_frame_nees(r) for r in results])
    frames = sum(len(r["t"]) for r in results)
    read_ms = float(
        np.average([r["read_cpu_ms"] for r in results], weights=[len(r["t"]) for r in results])
    )
    # A run on `jobs` cores loads the tables once per process, not once per scene.
    loads = min(jobs, len(results))
    load_s = float(np.mean([r["load_cpu_s"] for r in results]))
    load_ms = load_s * loads * 1e3 / frames
    per_frame = pool_rows["ours"]["cpu_ms_per_frame"] + read_ms + load_ms
    realtime = jobs * 1e3 / per_frame / RADAR_HZ
    # The start-up (imports, compiled kernels) is paid once per process before the first frame,
    # whatever the drive's length: not in the rate, shown with it spread over this split.
    startup_ms = startup_s * loads * 1e3 / frames
    realtime_startup = jobs * 1e3 / (per_frame + startup_ms) / RADAR_HZ
    print(
        f"\nours with reading: {per_frame:.2f} CPU ms/frame (ours "
        f"{pool_rows['ours']['cpu_ms_per_frame']:.2f}, sweeps {read_ms:.2f}, tables {load_s:.2f} s "
        f"x {loads} processes = {load_ms:.2f}) -> {realtime:.1f}x real time on {jobs} cores "
        f"({frames} frames; bench wall {wall:.0f} s for 3 methods)\n"
        f"start-up before the first frame (imports, compiled kernels): {startup_s:.2f} CPU s per "
        f"process; spread over these {frames} frames (+{startup_ms:.2f} ms/frame) "
        f"{realtime_startup:.1f}x"
    )
    spread = (
        seed_spread(dataroot, version, groups, overrides, jobs, seeds, per_scene)
        if seeds > 1
        else None
    )
    sequence = None
    if not chain and len(groups) > 1 and all(len(g) == 1 for g in groups):
        if spread is not None:
            alone = {s: row["ours"]["median_m"] for s, row in spread["scenes"].items()}
        else:
            alone = {s: rows["ours"]["ate_m"] for s, rows in per_scene.items()}
            alone["pooled"] = pool_rows["ours"]["ate_m"]
        sequence = sequence_runs(
            dataroot, version, [g[0] for g in groups], overrides, jobs, seeds, alone
        )
    lines = verdicts(per_scene, pool_rows, heading, nees, realtime, spread)
    print("\n".join(lines))
    return {
        "doppler_seed_spread": spread,
        "ours_in_one_run": sequence,
        "dataroot": str(dataroot),
        "version": version,
        "scenes": {s: {mm: _public(x) for mm, x in rows.items()} for s, rows in per_scene.items()},
        "pooled": pool_rows,
        "doppler_heading": heading,
        "doppler_heading_nominal_calibration": raw_heading,
        "doppler_calibration": cals,
        "key_frame_nees_mean": float(np.nanmean(nees)) if nees.size else None,
        "key_frame_nees_median": float(np.nanmedian(nees)) if nees.size else None,
        "ours_realtime_factor": realtime,
        "ours_realtime_factor_with_startup": realtime_startup,
        "startup_cpu_s": startup_s,
        "cpu_ms_per_frame": {
            "ours": pool_rows["ours"]["cpu_ms_per_frame"],
            "sweeps": read_ms,
            "tables": load_ms,
        },
        "verdicts": lines,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--dataroot", type=Path, default=REAL_DATAROOT)
    ap.add_argument("--version", default="v1.0-mini")
    ap.add_argument("--scenes", default=None, help="comma-separated scene names (default: all)")
    ap.add_argument(
        "--synthetic", action="store_true", help="the synthetic city subset and long drive"
    )
    ap.add_argument("--work", type=Path, default=Path("/tmp/radarslam_bench_odometry"))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument(
        "--doppler-seeds",
        type=int,
        default=None,
        help="also run every method with this many Doppler RANSAC seeds and print the spread "
        "(default: 5 on real data, 1 on --synthetic; 1: the configured seed only)",
    )
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        help="odometry config override, e.g. fusion.gate_chi2=20",
    )
    args = ap.parse_args()
    odometry_config(args.set)  # a bad --set is one line here, not a traceback from every worker
    if args.doppler_seeds is not None and args.doppler_seeds < 1:
        print(f"error: --doppler-seeds {args.doppler_seeds}: need at least 1", file=sys.stderr)
        sys.exit(2)

    # Loaded before the workers fork, so that the one-time start-up is not charged to the first
    # segment each worker runs: it is measured apart, on a process of its own.
    import kiss_icp.kiss_icp  # noqa: F401

    import radarslam.odometry.baselines  # noqa: F401
    from radarslam.odometry import load_kernels

    load_kernels()
    startup_s = startup_cpu_s()

    summary = {}
    if args.synthetic:
        args.work.mkdir(parents=True, exist_ok=True)
        for name, root in synthetic_dataroots(args.work).items():
            summary[name] = evaluate(
                name, root, "v1.0-trainval", None, name == "long", args.jobs, args.set,
                args.doppler_seeds or 1, startup_s,
            )  # fmt: skip
    else:
        if not (args.dataroot / args.version).is_dir():
            print(
                f"error: {args.dataroot / args.version}: no such folder (the real nuScenes radar "
                "split lives in ../shared/data/nuscenes-mini-radar; pass --dataroot/--version, "
                "or --synthetic)",
                file=sys.stderr,
            )
            sys.exit(2)
        scenes = [s for s in args.scenes.split(",") if s] if args.scenes else None
        summary["real"] = evaluate(
            "real", args.dataroot, args.version, scenes, False, args.jobs, args.set,
            5 if args.doppler_seeds is None else args.doppler_seeds, startup_s,
        )  # fmt: skip
    if args.json:
        from radarslam.io.atomic import write_text_atomic

        write_text_atomic(args.json, json.dumps(summary, indent=2, default=float) + "\n")


if __name__ == "__main__":
    from _cli import guarded

    guarded(main)
