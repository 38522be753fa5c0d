"""``radarslam eval RESULTS_DIR``: metrics of a results folder (layout: docs/outputs.md).

For every session and for the whole run, odometry-only and SLAM side by side (a folder that
``radarslam odometry`` wrote holds odometry only: no SLAM rows, no loops):
ATE (SE(2)-aligned RMSE, and unaligned from the first pose), RPE per ``rpe_time_s`` seconds and per
``rpe_distance_m`` metres, KITTI-style drift, and loop-closure precision / recall from
``loops.csv``. Run-level numbers pool the per-session errors (each session aligned on its own) and,
for ATE, also align all sessions jointly with one transform (``ate_joint``), which is what shows
whether a multi-session map is consistent.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field, field_validator

from radarslam.config import StrictModel
from radarslam.errors import DataError
from radarslam.eval.loops import LoopEvalConfig, LoopMetrics, SessionGroundTruth, evaluate_loops
from radarslam.eval.metrics import (
    align_se2,
    ate,
    ate_clock_offsets,
    drift,
    path_lengths_m,
    rpe,
    to_xy_yaw,
    turn_scale,
    turn_scale_of_steps,
)
from radarslam.geometry import invert
from radarslam.io.atomic import write_json_atomic
from radarslam.io.loops import read_loops_csv_numbered
from radarslam.io.results import ResultsFolder, read_results, trajectory_path

log = logging.getLogger("radarslam.eval")

KINDS = ("odometry", "slam")


class EvalConfig(StrictModel):
    rpe_time_s: float = Field(1.0, gt=0)
    rpe_distance_m: float = Field(10.0, gt=0)
    drift_segment_lengths_m: tuple[float, ...] = (50.0, 100.0)
    max_time_diff_us: int = Field(10_000, ge=0)  # association of estimate and ground truth
    # The ground truth's clock is also read shifted by up to this (5 ms steps; 0: not at all)
    # to report the offset against the estimate's stamps that fits best, and the ATE there.
    clock_offset_max_ms: float = Field(100.0, ge=0, le=1000)
    # The turn scale (the estimate's heading change per degree of the ground truth's) is
    # reported where the ground truth turns at least this much in all (summed |change|).
    turn_scale_min_deg: float = Field(45.0, ge=0, le=100_000)
    # The similarity scale is reported where the ground truth drives at least this far: on a
    # drive that stands, the estimate's length is noise and the ratio means nothing.
    scale_min_path_m: float = Field(10.0, ge=0, le=1e7)
    loops: LoopEvalConfig = LoopEvalConfig()
    plots: bool = True

    @field_validator("drift_segment_lengths_m")
    @classmethod
    def _segment_lengths(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if not v:
            raise ValueError("needs at least one segment length")
        if not all(np.isfinite(x) and x > 0 for x in v):
            raise ValueError("segment lengths must be finite and > 0")
        return v


@dataclass
class TrajectoryMetrics:
    num_poses: int
    path_length_m: float
    ate_rmse_m: float  # SE(2)-aligned
    ate_along_m: float  # its share along the ground truth's heading (RMS)
    ate_cross_m: float  # and across it
    # Umeyama with scale (evo's correct_scale): ground-truth length / estimated length, above 1
    # where the estimate is short (a speed-scale error, or a path that winds), and the ATE there;
    # the scale is NaN where the truth drives less than scale_min_path_m.
    sim2_scale: float
    ate_sim2_m: float
    # The estimate's heading change per unit of the ground truth's, fitted step by step (above
    # 1: it turns too far); NaN where the truth turns less than turn_scale_min_deg in all.
    turn_scale: float
    turned_deg: float
    ate_max_m: float
    ate_first_rmse_m: float  # unaligned: first poses made to coincide
    ate_final_first_m: float  # last-pose error with first-pose alignment (open-loop drift)
    rpe_time_trans_rmse_m: float
    rpe_time_rot_rmse_deg: float
    rpe_dist_trans_rmse_m: float
    rpe_dist_rot_rmse_deg: float
    drift_pct: float
    drift_deg_per_100m: float
    # The ground truth's clock shifted by the offset that fits best (estimate stamps early: +):
    # the SE(2)-aligned ATE there. NaN when not searched or too short.
    clock_offset_ms: float = float("nan")
    ate_at_clock_offset_m: float = float("nan")

    def as_dict(self) -> dict:
        return {k: _clean(v) for k, v in self.__dict__.items()}


@dataclass
class EvalReport:
    results_dir: Path
    sessions: list[str]
    per_session: dict[str, dict[str, TrajectoryMetrics]]  # session -> kind -> metrics
    #: kind -> pooled numbers (None: nothing to pool), and ``components_joint``: a list
    run: dict[str, dict[str, Any]]
    loops: LoopMetrics | None
    config: EvalConfig
    kind: str = "slam"  # of the results folder: slam or odometry
    method: str | None = None  # the odometry method of an odometry folder, when recorded
    errors_over_time: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = field(
        default_factory=dict, repr=False
    )  # session -> kind -> (time_s, ATE errors)

    def as_dict(self) -> dict:
        return {
            "results_dir": str(self.results_dir),
            "kind": self.kind,
            "method": self.method,
            "sessions": self.sessions,
            "per_session": {
                s: {k: m.as_dict() for k, m in kinds.items()}
                for s, kinds in self.per_session.items()
            },
            "run": {k: {n: _clean(v) for n, v in d.items()} for k, d in self.run.items()},
            "loops": self.loops.as_dict() if self.loops is not None else None,
            "config": self.config.model_dump(mode="json"),
        }


def _clean(v):
    if isinstance(v, (float, np.floating)):
        return float(v) if np.isfinite(v) else None
    if isinstance(v, np.integer):
        return int(v)
    return v


# --- association ----------------------------------------------------------------------------


def associate(
    est_t: np.ndarray, gt_t: np.ndarray, max_diff_us: int
) -> tuple[np.ndarray, np.ndarray]:
    """Indices (i_est, i_gt) pairing each estimate with the nearest ground truth in time."""
    if gt_t.size == 0 or est_t.size == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    order = np.argsort(gt_t, kind="stable")
    g = gt_t[order]
    pos = np.clip(np.searchsorted(g, est_t), 1, len(g) - 1) if len(g) > 1 else np.zeros_like(est_t)
    left = np.clip(pos - 1, 0, len(g) - 1)
    right = np.clip(pos, 0, len(g) - 1)
    take_right = np.abs(g[right] - est_t) < np.abs(g[left] - est_t)
    nearest = np.where(take_right, right, left)
    ok = np.abs(g[nearest] - est_t) <= max_diff_us
    return np.nonzero(ok)[0], order[nearest[ok]]


# --- metrics -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class SessionErrors:
    """A session's per-pose errors, kept for pooling over the run."""

    ate_errors_m: np.ndarray  # SE(2)-aligned
    first_errors_m: np.ndarray  # first poses made to coincide
    turn_steps: tuple[np.ndarray, np.ndarray]  # TurnScaleResult.steps


def trajectory_metrics(
    est: np.ndarray,
    ref: np.ndarray,
    t_us: np.ndarray,
    cfg: EvalConfig,
    ref_track: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[TrajectoryMetrics, SessionErrors]:
    """Metrics of ``est`` against ``ref`` (associated pose by pose, stamps ``t_us``) and the
    errors they pool from; ``ref_track`` (stamps, poses): the whole ground truth, for the
    clock-offset search."""
    a = ate(est, ref, align="se2")
    a_sim = ate(est, ref, align="sim2")
    clock = None
    if ref_track is not None and cfg.clock_offset_max_ms > 0:
        clock = ate_clock_offsets(
            est, t_us, ref_track[1], ref_track[0], cfg.clock_offset_max_ms * 1e-3
        )
    f = ate(est, ref, align="first")
    turn = turn_scale(est, ref, cfg.turn_scale_min_deg)
    r_t = rpe(est, ref, t_us, delta=cfg.rpe_time_s, unit="s")
    r_d = rpe(est, ref, t_us, delta=cfg.rpe_distance_m, unit="m")
    dr = drift(est, ref, segment_lengths_m=cfg.drift_segment_lengths_m)
    length_m = float(path_lengths_m(to_xy_yaw(ref))[-1])
    m = TrajectoryMetrics(
        num_poses=len(est),
        path_length_m=length_m,
        ate_rmse_m=a.rmse_m,
        ate_along_m=a.along_rmse_m,
        ate_cross_m=a.cross_rmse_m,
        sim2_scale=a_sim.alignment.scale if length_m >= cfg.scale_min_path_m else float("nan"),
        ate_sim2_m=a_sim.rmse_m,
        turn_scale=turn.scale,
        turned_deg=turn.turned_deg,
        ate_max_m=a.max_m,
        ate_first_rmse_m=f.rmse_m,
        ate_final_first_m=float(f.errors_m[-1]),
        rpe_time_trans_rmse_m=r_t.trans_rmse_m,
        rpe_time_rot_rmse_deg=r_t.rot_rmse_deg,
        rpe_dist_trans_rmse_m=r_d.trans_rmse_m,
        rpe_dist_rot_rmse_deg=r_d.rot_rmse_deg,
        drift_pct=dr.translation_pct,
        drift_deg_per_100m=dr.rotation_deg_per_100m,
    )
    if clock is not None:
        m.clock_offset_ms = 1e3 * clock.best_offset_s
        m.ate_at_clock_offset_m = clock.best_rmse_m
    return m, SessionErrors(a.errors_m, f.errors_m, turn.steps)


def evaluate_results(
    results_dir: str | Path,
    config: EvalConfig | None = None,
    write: bool = True,
    name: str | Path | None = None,
) -> EvalReport:
    """Metrics of a results folder, written into it as ``metrics.json`` and ``plots/*.png``
    (``write``). ``name``: the folder's path to report, when it is evaluated before being moved
    there (default ``results_dir``)."""
    cfg = config or EvalConfig()
    folder = read_results(results_dir)
    per_session: dict[str, dict[str, TrajectoryMetrics]] = {}
    errors_t: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = {}
    pooled: dict[str, dict[str, list]] = {
        k: {"ate": [], "first": [], "est": [], "ref": [], "turn": []} for k in KINDS
    }
    gt_for_loops: dict[str, SessionGroundTruth] = {}
    for s in folder.sessions:
        traj = folder.trajectories[s]
        gt_t, gt_p = traj["gt"]
        if len(gt_t) < 2:
            gt_file = trajectory_path(folder.path, "gt", s)
            raise DataError(f"{gt_file}: {len(gt_t)} ground-truth poses; need at least 2")
        gt_for_loops[s] = SessionGroundTruth(gt_t, gt_p)
        per_session[s] = {}
        errors_t[s] = {}
        for kind in KINDS:
            if kind not in traj:
                continue
            est_t, est_p = traj[kind]
            i_e, i_g = associate(est_t, gt_t, cfg.max_time_diff_us)
            if len(i_e) < 2:
                raise DataError(
                    f"{trajectory_path(folder.path, kind, s)}: only {len(i_e)} poses match the "
                    f"ground truth in time (within {cfg.max_time_diff_us} us); need at least 2"
                )
            e, r, t = est_p[i_e], gt_p[i_g], est_t[i_e]
            m, errs = trajectory_metrics(e, r, t, cfg, (gt_t, gt_p))
            per_session[s][kind] = m
            errors_t[s][kind] = ((t - t[0]) / 1e6, errs.ate_errors_m)
            pooled[kind]["ate"].append(errs.ate_errors_m)
            pooled[kind]["first"].append(errs.first_errors_m)
            pooled[kind]["turn"].append(errs.turn_steps)
            # Odometry sessions start in frames of their own: placed on their ground-truth
            # first pose they share the world, and their joint ATE is the baseline of SLAM's.
            pooled[kind]["est"].append(r[0] @ invert(e[0]) @ e if kind == "odometry" else e)
            pooled[kind]["ref"].append(r)
            pooled[kind].setdefault("session", []).append(s)
    run: dict[str, dict[str, Any]] = {}
    for kind in KINDS:
        p = pooled[kind]
        if not p["ate"]:
            continue
        all_err = np.concatenate(p["ate"])
        first_err = np.concatenate(p["first"])
        # SLAM sessions outside the anchored map live in their own frames: one alignment
        # across them would measure nothing, so the joint ATE covers the anchored map, for the
        # odometry too (the same sessions: its joint ATE is the baseline of SLAM's).
        in_joint = [
            i
            for i, s in enumerate(p["session"])
            if folder.components is None or s in folder.components[0]
        ]

        def joint(rows: list[int], p: dict = p) -> float | None:
            if not rows:
                return None  # nothing to align jointly
            return ate(
                np.concatenate([p["est"][i] for i in rows]),
                np.concatenate([p["ref"][i] for i in rows]),
                align="se2",
            ).rmse_m

        joint_rmse_m = joint(in_joint)
        # Each component of several sessions aligned on its own: whether the sessions a run
        # linked outside the anchored map agree with each other (the odometry over the same
        # sessions, each started on its ground truth, is the baseline).
        by_component = []
        for index, comp in enumerate(folder.components or []):
            rows = [i for i, s in enumerate(p["session"]) if s in comp]
            if len(rows) >= 2:
                by_component.append(
                    {
                        "component": index,
                        "sessions": [p["session"][i] for i in rows],
                        "ate_joint_rmse_m": joint(rows),
                    }
                )
        run[kind] = {
            "num_sessions": len(p["ate"]),
            "num_poses": int(all_err.size),
            "ate_rmse_m": float(np.sqrt(np.mean(all_err**2))),
            "ate_first_rmse_m": float(np.sqrt(np.mean(first_err**2))),
            "ate_joint_rmse_m": joint_rmse_m,
            "turn_scale": turn_scale_of_steps(
                np.concatenate([dh for dh, _ in p["turn"]]),
                np.concatenate([de for _, de in p["turn"]]),
                cfg.turn_scale_min_deg,
            ).scale,
            "joint_sessions": len(in_joint),
            "components_joint": by_component,
        }
    loop_metrics = None
    if folder.loops_path is not None:
        numbered = read_loops_csv_numbered(folder.loops_path)
        loop_metrics = evaluate_loops(
            [lc for _, lc in numbered],
            gt_for_loops,
            cfg.loops,
            folder.sessions,
            labels=[f"{folder.loops_path}:{line}" for line, _ in numbered],
            continues=folder.continues,
        )
    report = EvalReport(
        results_dir=folder.path if name is None else Path(name),
        sessions=folder.sessions,
        per_session=per_session,
        run=run,
        loops=loop_metrics,
        config=cfg,
        kind=folder.kind,
        method=folder.method,
        errors_over_time=errors_t,
    )
    if write:
        write_json_atomic(folder.path / "metrics.json", report.as_dict())
        if cfg.plots:
            write_plots(folder, report)
    return report


def _display_slam(folder: ResultsFolder, session: str) -> np.ndarray | None:
    """SLAM positions to draw: as estimated in the anchored map; a session of another component
    (its own frame) is drawn after one SE(2) alignment of its whole component to ground truth."""
    tr = folder.trajectories[session].get("slam")
    if tr is None:
        return None
    comps = folder.components
    if comps is None or session in comps[0]:
        return tr[1][:, :2, 3]
    comp = next((c for c in comps if session in c), [session])
    est = np.concatenate([folder.trajectories[s]["slam"][1] for s in comp])
    ref = np.concatenate([folder.trajectories[s]["gt"][1] for s in comp])
    if len(est) != len(ref):
        return tr[1][:, :2, 3]
    return align_se2(est, ref).apply(to_xy_yaw(tr[1]))[:, :2]


def _display_odometry(folder: ResultsFolder, session: str) -> np.ndarray | None:
    """Odometry positions to draw, first pose put on the ground truth's (shows its drift)."""
    tr, gt = folder.trajectories[session].get("odometry"), folder.trajectories[session]["gt"]
    if tr is None or not len(tr[1]) or not len(gt[1]):
        return None
    start = gt[1][0] @ np.linalg.inv(tr[1][0])
    return (start @ tr[1])[:, :2, 3]


def write_plots(folder: ResultsFolder, report: EvalReport) -> None:
    from radarslam.eval.plots import (
        ErrorSeries,
        LoopSegment,
        TrajectoryPlotData,
        plot_errors_over_time,
        plot_trajectories,
    )

    def xy(kind, s):
        tr = folder.trajectories[s].get(kind)
        return None if tr is None else tr[1][:, :2, 3]

    lookup: dict[str, dict[int, np.ndarray]] = {}
    for s in folder.sessions:
        for kind in ("slam", "odometry"):
            tr = folder.trajectories[s].get(kind)
            if tr is not None:
                lookup.setdefault(s, {int(t): p[:2, 3] for t, p in zip(tr[0], tr[1], strict=True)})
    segments = []
    if report.loops is not None:
        for j in report.loops.judgements:
            lp = j.loop
            if not lp.accepted:
                continue
            a = lookup.get(lp.query.session, {}).get(lp.query_timestamp_us)
            b = lookup.get(lp.candidate.session, {}).get(lp.candidate_timestamp_us)
            if a is not None and b is not None:
                segments.append(LoopSegment(a, b, j.correct))
    in_map = folder.components[0] if folder.components else folder.sessions
    trajs = [
        TrajectoryPlotData(
            s if s in in_map else f"{s} (own map, aligned to GT)",
            _display_slam(folder, s),
            xy("gt", s),
            _display_odometry(folder, s),
        )
        for s in folder.sessions
    ]
    plots = folder.path / "plots"
    title = "SLAM vs odometry vs GT" if folder.kind == "slam" else "odometry vs GT"
    plot_trajectories(plots / "trajectories.png", trajs, segments, title=title)
    for s in folder.sessions:
        errs = report.errors_over_time.get(s, {})
        plot_errors_over_time(
            plots / f"errors_{s}.png",
            [ErrorSeries(s, v[0], {k: v[1]}) for k, v in errs.items()],
            title=f"{s}: ATE position error (SE(2)-aligned)",
        )
