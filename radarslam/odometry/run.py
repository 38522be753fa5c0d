"""Whole-scene odometry runs and their outputs (TUM / KITTI poses with the ground truth alongside).

Scenes are processed in the order given. Consecutive scenes continue one odometry *segment* when
the next scene starts within ``fusion.max_gap_s`` of the previous one's last frame (consecutive
drives of one log); otherwise the odometry restarts from ``initial_pose`` (a new segment).
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from radarslam.errors import ConfigError, DataError
from radarslam.odometry.config import OdometryConfig
from radarslam.types import RADAR_CHANNELS, SceneInfo

log = logging.getLogger("radarslam.odometry")

#: A scene's Doppler is implausible when fewer of its frames than this share have a valid fit
#: (among frames with enough points for one)...
MIN_VALID_DOPPLER_SHARE = 0.5
#: ...or when the fits' inliers are fewer than this share of their points. A static world is
#: most of what a radar sees in traffic (0.92-0.95 on the synthetic drives); Doppler values
#: that are noise leave the RANSAC a few percent (0.05 with random values on the same drives).
MIN_DOPPLER_INLIER_SHARE = 0.3


@dataclass
class DopplerHealth:
    """The Doppler fits of one scene, to say when they cannot be trusted: the odometry then runs
    on registration and a constant-velocity guess, and its error grows without a sign."""

    min_points: int = 3
    frames: int = 0  # frames with enough points for a fit
    valid: int = 0
    inliers: int = 0
    points: int = 0  # points of the valid fits

    def add(self, fit) -> None:
        if fit is None or fit.num_points < self.min_points:
            return
        self.frames += 1
        if fit.valid:
            self.valid += 1
            self.inliers += int(fit.num_inliers)
            self.points += int(fit.num_points)

    def problem(self) -> str | None:
        """Why the Doppler of this scene is implausible (each reason that applies), or
        ``None``."""
        if not self.frames:
            return None
        reasons = []
        share = self.valid / self.frames
        if share < MIN_VALID_DOPPLER_SHARE:
            reasons.append(
                f"only {self.valid} of {self.frames} frames have a valid Doppler fit "
                f"({share:.0%}; expected at least {MIN_VALID_DOPPLER_SHARE:.0%})"
            )
        ratio = self.inliers / self.points if self.points else None
        if ratio is not None and ratio < MIN_DOPPLER_INLIER_SHARE:
            reasons.append(
                f"the Doppler fits keep only {ratio:.0%} of their points as static-world inliers "
                f"(expected at least {MIN_DOPPLER_INLIER_SHARE:.0%}; corrupt radial velocities?)"
            )
        return "; ".join(reasons) or None


@dataclass
class OdometryTrajectory:
    """Per-frame odometry of one run (one or several scenes), index-aligned arrays."""

    method: str
    timestamps_us: np.ndarray  # (N,) int64
    poses: np.ndarray  # (N, 4, 4) estimated world_from_ego
    ground_truth: np.ndarray  # (N, 4, 4)
    relative_covariances: np.ndarray  # (N, 3, 3) of prev_ego_from_ego (NaN when not reported)
    scene_names: list[str]
    segments: np.ndarray  # (N,) int: index of the continuous odometry segment
    is_key_frame: np.ndarray  # (N,) bool
    sample_tokens: list[str]
    statuses: list[str]
    num_points: np.ndarray  # (N,) int
    processing_ms: np.ndarray  # (N,) float
    #: Key frames (after a segment's first): motion since the previous key frame and covariance.
    key_frame_motions: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    #: Doppler calibration estimated by the filter at the end of the run for the rig of the
    #: last scene (``ours`` only).
    calibration: dict | None = None
    #: Every radar rig's calibration (``ours`` only), each naming its rig and scenes: scenes
    #: of several vehicles each get their own.
    calibrations: list[dict] = field(default_factory=list)

    def __len__(self) -> int:
        return len(self.timestamps_us)

    @property
    def duration_s(self) -> float:
        """Sum over segments of their time span."""
        total = 0.0
        for s in np.unique(self.segments):
            t = self.timestamps_us[self.segments == s]
            total += (t[-1] - t[0]) * 1e-6 if len(t) > 1 else 0.0
        return total

    def scene(self, name: str) -> OdometryTrajectory:
        idx = [i for i, s in enumerate(self.scene_names) if s == name]
        if not idx:
            raise DataError(f"scene {name!r} is not in this odometry run")
        return self.subset(np.array(idx))

    def subset(self, idx: np.ndarray) -> OdometryTrajectory:
        remap = {int(j): i for i, j in enumerate(idx)}
        return OdometryTrajectory(
            method=self.method,
            timestamps_us=self.timestamps_us[idx],
            poses=self.poses[idx],
            ground_truth=self.ground_truth[idx],
            relative_covariances=self.relative_covariances[idx],
            scene_names=[self.scene_names[i] for i in idx],
            segments=self.segments[idx],
            is_key_frame=self.is_key_frame[idx],
            sample_tokens=[self.sample_tokens[i] for i in idx],
            statuses=[self.statuses[i] for i in idx],
            num_points=self.num_points[idx],
            processing_ms=self.processing_ms[idx],
            key_frame_motions={
                remap[k]: v for k, v in self.key_frame_motions.items() if int(k) in remap
            },
        )


def run_odometry(
    reader,
    scenes: Iterable[str | SceneInfo],
    config: OdometryConfig | None = None,
    *,
    method: str = "ours",
    progress: bool = True,
    max_frames_per_scene: int | None = None,
    frame_stride: int = 1,
) -> OdometryTrajectory:
    """Run ``method`` (``ours``, ``doppler`` or ``kiss-icp``) over ``scenes`` of a
    :class:`~radarslam.nuscenes.reader.NuScenesRadar` and collect the per-frame estimates.

    ``scenes``: names or :class:`SceneInfo` (one name or SceneInfo alone is one scene), each scene
    at most once (:class:`DataError` otherwise: its frames would repeat timestamps).
    ``frame_stride`` k: every k-th frame only (a strided calibration pass), the gap that starts
    a new segment scaled by k; ``max_frames_per_scene`` counts the frames read."""
    config = config or OdometryConfig()
    if isinstance(scenes, (str, SceneInfo)):
        scenes = [scenes]  # one scene, not a sequence of characters
    infos = [reader.scene(s) for s in scenes]  # unknown names fail before any work
    if not infos:
        raise DataError("run_odometry: no scene given")
    if max_frames_per_scene is not None and (
        isinstance(max_frames_per_scene, bool)
        or not isinstance(max_frames_per_scene, (int, np.integer))
        or max_frames_per_scene < 1
    ):
        raise ConfigError(
            f"max_frames_per_scene must be an integer >= 1 or None, got {max_frames_per_scene!r}"
        )
    seen: set[str] = set()
    for info in infos:
        if info.name in seen:
            raise DataError(
                f"scene {info.name!r} is given more than once; each scene can be run once "
                "(its frames would repeat timestamps)"
            )
        seen.add(info.name)
    if (
        isinstance(frame_stride, bool)
        or not isinstance(frame_stride, (int, np.integer))
        or frame_stride < 1
    ):
        raise ConfigError(f"frame_stride must be an integer >= 1, got {frame_stride!r}")
    kw = {"progress": progress, "max_frames": max_frames_per_scene, "stride": int(frame_stride)}
    cal = config.fusion.calibration
    if method == "ours" and cal.passes > 1 and cal.yaw_bias_model == "mounting":
        return _self_calibrated(reader, infos, config, **kw)
    return _run_once(reader, infos, config, method, **kw)


def _run_once(
    reader,
    infos: Sequence[SceneInfo],
    config: OdometryConfig,
    method: str,
    *,
    progress: bool,
    max_frames: int | None,
    stride: int,
    calibration_pass: bool = False,
) -> OdometryTrajectory:
    """One pass of ``method`` over the scenes (arguments checked by :func:`run_odometry`). A
    ``calibration_pass`` names its progress bar so and does not warn of unreliable Doppler
    fits: the run proper that follows says it once."""
    from radarslam.nuscenes.filters import RadarPointFilter
    from radarslam.odometry.baselines import make_odometry

    pc = config.points
    filters = RadarPointFilter(pc.invalid_states, pc.dynprop_states, pc.ambig_states)
    odo = make_odometry(method, config)
    rows: dict[str, list] = {k: [] for k in _ROW_KEYS}
    kf: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    segment = -1
    last_t: int | None = None
    desc = "calibration pass" if calibration_pass else "odometry"
    bar = _progress(progress, infos, reader, max_frames, stride, desc)
    max_gap_us = config.fusion.max_gap_s * 1e6 * stride
    try:
        for info in infos:
            health = DopplerHealth(config.doppler.min_points)
            seen: set[str] = set()
            frames = reader.iter_frames(info, filters=filters, stride=stride)
            for k, frame in enumerate(frames):
                if max_frames is not None and k >= max_frames:
                    break
                seen.update(frame.sweeps)
                gap_ok = last_t is not None and 0 < frame.timestamp_us - last_t <= max_gap_us
                if not gap_ok:
                    odo.reset()
                    segment += 1
                res = odo.process(frame)
                health.add(res.doppler)
                last_t = frame.timestamp_us
                if res.key_frame_motion is not None:
                    kf[len(rows["t"])] = (res.key_frame_motion, res.key_frame_covariance)
                for key, value in (
                    ("t", res.timestamp_us),
                    ("pose", res.world_from_ego),
                    ("gt", res.ground_truth),
                    ("cov", res.relative_covariance),
                    ("scene", info.name),
                    ("seg", segment),
                    ("kf", res.is_key_frame),
                    ("token", res.sample_token),
                    ("status", res.status),
                    ("npts", res.num_points),
                    ("ms", res.timing.total_ms),
                ):
                    rows[key].append(value)
                if bar is not None:
                    bar.update(1)
            why = health.problem()
            if why is not None and not calibration_pass:
                log.warning("scene %s: %s: its odometry is unreliable", info.name, why)
            missing = [ch for ch in RADAR_CHANNELS if ch not in seen]
            if seen and missing and not calibration_pass:
                # a radar the dataroot does not list (sensor.json) or never recorded here
                log.warning(
                    "scene %s: no sweep from %s: the odometry runs on the other radars",
                    info.name,
                    ", ".join(missing),
                )
    finally:
        if bar is not None:
            bar.close()
    if not rows["t"]:
        raise DataError(f"no radar frame in scene(s) {', '.join(i.name for i in infos)}")
    return OdometryTrajectory(
        method=method,
        timestamps_us=np.asarray(rows["t"], dtype=np.int64),
        poses=np.stack(rows["pose"]),
        ground_truth=np.stack(rows["gt"]),
        relative_covariances=np.stack(rows["cov"]),
        scene_names=rows["scene"],
        segments=np.asarray(rows["seg"], dtype=np.int64),
        is_key_frame=np.asarray(rows["kf"], dtype=bool),
        sample_tokens=rows["token"],
        statuses=rows["status"],
        num_points=np.asarray(rows["npts"], dtype=np.int64),
        processing_ms=np.asarray(rows["ms"], dtype=np.float64),
        key_frame_motions=kf,
        calibration=odo.calibration.as_dict() if hasattr(odo, "calibration") else None,
        calibrations=[c.as_dict() for c in getattr(odo, "calibrations", [])],
    )


def single_pass(config: OdometryConfig, mounting_yaw_deg: dict[str, float]) -> OdometryConfig:
    """``config`` with one pass and these mounting yaws applied to every sweep."""
    cal = config.fusion.calibration.model_copy(update={"passes": 1})
    fusion = config.fusion.model_copy(update={"calibration": cal})
    return config.model_copy(update={"fusion": fusion, "mounting_yaw_deg": mounting_yaw_deg})


def second_pass(config: OdometryConfig, first_calibration: dict | None) -> OdometryConfig:
    """The self-calibration pass's config: the mounting yaws given in ``config`` plus those the
    first pass estimated (its ``calibration.as_dict()``), applied from the first frame; with
    ``calibration.common_yaw: median`` the estimate's median is taken out first."""
    given = dict(config.mounting_yaw_deg)
    estimated = (first_calibration or {}).get("mounting_yaw_error_deg", {})
    shift = 0.0
    if estimated and config.fusion.calibration.common_yaw == "median":
        shift = float(np.median([estimated.get(ch, 0.0) for ch in RADAR_CHANNELS]))
    applied = {ch: given.get(ch, 0.0) + estimated.get(ch, 0.0) - shift for ch in RADAR_CHANNELS}
    return single_pass(config, applied)


def total_calibration(applied: OdometryConfig, residual: dict) -> dict:
    """The second pass's calibration reported as the vehicle's total mounting error: what was
    applied plus what the filter found left."""
    out = dict(residual)
    left = residual.get("mounting_yaw_error_deg", {})
    out["mounting_yaw_error_deg"] = {
        ch: applied.mounting_yaw_deg.get(ch, 0.0) + left.get(ch, 0.0) for ch in RADAR_CHANNELS
    }
    out["passes"] = 2
    return out


def _self_calibrated(reader, infos, config, *, progress, max_frames, stride):
    """Two passes (``fusion.calibration.passes: 2``): the second applies the mounting yaws the
    first estimated (plus any given ones) to every sweep from the start, so neither the map nor
    the early Doppler fits carry the error while the filter converges."""
    from radarslam.odometry.calibration import count_rigs

    kw = {"progress": progress, "max_frames": max_frames}
    given = single_pass(config, dict(config.mounting_yaw_deg))
    rigs = count_rigs(reader, infos)
    if rigs > 1:
        # One set of mounting yaws cannot be applied to every sweep of several cars.
        log.warning(
            "the scenes come from %d radar rigs (nominal extrinsics differ); the calibration "
            "pass applies to one rig, so the single pass's per-rig estimates are kept",
            rigs,
        )
        return _run_once(reader, infos, given, "ours", stride=stride, **kw)
    pass_stride = stride * config.fusion.calibration.pass_frame_stride
    first = _run_once(reader, infos, given, "ours", stride=pass_stride, calibration_pass=True, **kw)
    applied = second_pass(config, first.calibration)
    second = _run_once(reader, infos, applied, "ours", stride=stride, **kw)
    return dataclasses.replace(
        second,
        calibration=total_calibration(applied, second.calibration or {}),
        processing_ms=second.processing_ms + _spread(first, second),
    )


def _spread(first: OdometryTrajectory, second: OdometryTrajectory) -> np.ndarray:
    """The first pass's CPU per frame of the second (a strided pass ran fewer frames): each
    scene's total shared out over that scene's frames, so per-scene and pooled costs add up."""
    scenes, of_second = np.unique(np.asarray(second.scene_names), return_inverse=True)
    at = np.searchsorted(scenes, np.asarray(first.scene_names))
    known = at < len(scenes)
    known[known] = scenes[at[known]] == np.asarray(first.scene_names)[known]
    spent = np.bincount(at[known], weights=first.processing_ms[known], minlength=len(scenes))
    return (spent / np.bincount(of_second, minlength=len(scenes)))[of_second]


_ROW_KEYS = ("t", "pose", "gt", "cov", "scene", "seg", "kf", "token", "status", "npts", "ms")


def _progress(
    enabled: bool,
    infos: Sequence[SceneInfo],
    reader,
    max_frames: int | None,
    stride: int = 1,
    desc: str = "odometry",
):
    if not enabled:
        return None
    from tqdm import tqdm

    counts = (-(-reader.frame_count(i) // stride) for i in infos)
    total = sum(n if max_frames is None else min(n, max_frames) for n in counts)
    return tqdm(total=total or None, unit="frame", desc=desc, leave=False)


# --- outputs -------------------------------------------------------------------------------------


def write_outputs(traj: OdometryTrajectory, out_dir: str | Path, config: OdometryConfig) -> dict:
    """Write the odometry results folder (:mod:`radarslam.io.results`, kind ``odometry``): per
    scene ``odometry_<scene>.{tum,kitti}``, ``gt_<scene>.{tum,kitti}`` and
    ``key_frames_<scene>.csv``, plus ``config.yaml``, ``summary.json`` (metrics per scene and of
    the run, the Doppler calibration) and ``run.json``; returns the summary.

    The folder is written as a whole: a re-run with fewer scenes leaves no file of the others,
    an interrupted one leaves the previous folder."""
    from radarslam.config import dump_config
    from radarslam.io.atomic import write_json_atomic, write_text_atomic
    from radarslam.io.results import key_frames_path, write_results_folder, write_trajectories

    names = list(dict.fromkeys(traj.scene_names))
    summary: dict = {"method": traj.method, "scenes": {}}

    def contents(out: Path) -> None:
        for name in names:
            sub = traj.scene(name)
            write_trajectories(
                out, name, sub.timestamps_us, {"odometry": sub.poses, "gt": sub.ground_truth}
            )
            write_text_atomic(key_frames_path(out, name), _key_frames_csv(sub))
            summary["scenes"][name] = scene_metrics(sub)
        summary["total"] = scene_metrics(traj)
        if traj.calibration is not None:
            summary["doppler_calibration"] = traj.calibration
        if len(traj.calibrations) > 1:
            summary["doppler_calibration_by_rig"] = traj.calibrations
        write_text_atomic(out / "config.yaml", dump_config(config))
        write_json_atomic(out / "summary.json", summary)

    write_results_folder(out_dir, names, "odometry", contents, method=traj.method)
    return summary


def _key_frames_csv(traj: OdometryTrajectory) -> str:
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    cov_names = [f"cov_{a}{b}" for a in ("x", "y", "t") for b in ("x", "y", "t")]
    w.writerow(["timestamp_us", "sample_token", "dx_m", "dy_m", "dyaw_rad", *cov_names])
    for i in np.flatnonzero(traj.is_key_frame):
        motion, cov = traj.key_frame_motions.get(int(i), (None, None))
        if motion is None:
            vals = [""] * 12
        else:
            vals = [
                repr(float(motion[0, 3])),
                repr(float(motion[1, 3])),
                repr(float(np.arctan2(motion[1, 0], motion[0, 0]))),
                *(repr(float(v)) for v in np.asarray(cov).ravel()),
            ]
        w.writerow([int(traj.timestamps_us[i]), traj.sample_tokens[i], *vals])
    return buf.getvalue()


def scene_metrics(traj: OdometryTrajectory) -> dict:
    """ATE (SE(2)-aligned), RPE per 1 s and per 10 m, KITTI drift, path length and speed,
    computed per continuous segment and pooled (length-weighted for drift)."""
    from radarslam.eval import metrics as m

    ates, rpe_s, rpe_m, drifts, weights = [], [], [], [], []
    length = 0.0
    for s in np.unique(traj.segments):
        sel = traj.segments == s
        if sel.sum() < 3:
            continue
        est, gt, t = traj.poses[sel], traj.ground_truth[sel], traj.timestamps_us[sel]
        seg_len = float(m.path_lengths_m(m.to_xy_yaw(gt))[-1])
        length += seg_len
        ates.append((m.ate(est, gt, align="se2").rmse_m, int(sel.sum())))
        r1 = _try(lambda est=est, gt=gt, t=t: m.rpe(est, gt, t, 1.0, "s"))
        r10 = _try(lambda est=est, gt=gt: m.rpe(est, gt, None, 10.0, "m"))
        for r, acc in ((r1, rpe_s), (r10, rpe_m)):
            if r is not None and r.count:
                acc.append((r.trans_rmse_m, r.count))
        d = _try(lambda est=est, gt=gt: m.drift(est, gt, (100.0,)))
        if d is not None and np.isfinite(d.translation_pct):
            drifts.append(d.translation_pct)
            weights.append(seg_len)
    return {
        "frames": len(traj),
        "path_length_m": length,
        "duration_s": traj.duration_s,
        "ate_rmse_m": _pool_rms(ates),
        "rpe_1s_rmse_m": _pool_rms(rpe_s),
        "rpe_10m_rmse_m": _pool_rms(rpe_m),
        "drift_pct": float(np.average(drifts, weights=weights)) if drifts else None,
        "mean_ms_per_frame": float(np.mean(traj.processing_ms)),
    }


def _try(fn):
    try:
        return fn()
    except DataError:
        return None


def _pool_rms(pairs: list[tuple[float, int]]) -> float | None:
    pairs = [(v, n) for v, n in pairs if v is not None and np.isfinite(v) and n > 0]
    if not pairs:
        return None
    return float(np.sqrt(sum(v * v * n for v, n in pairs) / sum(n for _, n in pairs)))


def summary_json(summary: dict) -> str:
    return json.dumps(summary, indent=2)
