"""PNG plots (matplotlib Agg, imported lazily; each figure written atomically).

- :func:`plot_trajectories`: SLAM estimate, odometry and ground truth in bird's-eye view, accepted
  loop closures drawn as segments (green correct, red wrong, grey when not judged).
- :func:`plot_errors_over_time`: per-key-frame ATE position error of SLAM and odometry.
- :func:`plot_map_bev`: the static map as a bird's-eye-view scatter with the trajectory on top.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from radarslam.io.atomic import atomic_path


@dataclass(frozen=True)
class TrajectoryPlotData:
    name: str
    est_xy: np.ndarray | None = None  # (N, 2) SLAM
    gt_xy: np.ndarray | None = None
    odom_xy: np.ndarray | None = None


@dataclass(frozen=True)
class LoopSegment:
    query_xy: np.ndarray  # (2,) where the query is drawn
    candidate_xy: np.ndarray
    correct: bool | None = None


@dataclass(frozen=True)
class ErrorSeries:
    name: str
    time_s: np.ndarray
    errors: dict[str, np.ndarray] = field(default_factory=dict)  # label -> (N,) metres


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path: str | Path) -> None:
    plt = _pyplot()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120, bbox_inches="tight", format="png")
    plt.close(fig)


def plot_trajectories(
    path: str | Path,
    trajectories: Sequence[TrajectoryPlotData],
    loops: Sequence[LoopSegment] = (),
    title: str = "trajectory",
) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 8))
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    for n, tr in enumerate(trajectories):
        c = colors[n % len(colors)]
        if tr.gt_xy is not None and len(tr.gt_xy):
            ax.plot(tr.gt_xy[:, 0], tr.gt_xy[:, 1], "--", color="k", lw=1.0,
                    label="ground truth" if n == 0 else None)  # fmt: skip
        if tr.odom_xy is not None and len(tr.odom_xy):
            ax.plot(tr.odom_xy[:, 0], tr.odom_xy[:, 1], ":", color=c, lw=1.0,
                    label=f"{tr.name} odometry")  # fmt: skip
        if tr.est_xy is not None and len(tr.est_xy):
            ax.plot(tr.est_xy[:, 0], tr.est_xy[:, 1], "-", color=c, lw=1.5, label=f"{tr.name} SLAM")
    drawn = set()
    for lp in loops:
        kind = "unjudged" if lp.correct is None else ("correct" if lp.correct else "wrong")
        color = {"correct": "tab:green", "wrong": "tab:red", "unjudged": "0.5"}[kind]
        ax.plot([lp.query_xy[0], lp.candidate_xy[0]], [lp.query_xy[1], lp.candidate_xy[1]],
                color=color, lw=0.8, alpha=0.8,
                label=f"loop ({kind})" if kind not in drawn else None)  # fmt: skip
        # revisits of the same spot give near zero-length segments: mark the ends too
        ax.plot([lp.query_xy[0], lp.candidate_xy[0]], [lp.query_xy[1], lp.candidate_xy[1]],
                "o", color=color, ms=3, alpha=0.8)  # fmt: skip
        drawn.add(kind)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    _save(fig, path)


def plot_errors_over_time(path: str | Path, series: Sequence[ErrorSeries], title: str = "") -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(9, 4))
    for s in series:
        for label, err in s.errors.items():
            ax.plot(s.time_s, err, lw=1.0, label=f"{s.name} {label}")
    ax.set_xlabel("time since first key frame [s]")
    ax.set_ylabel("position error [m]")
    ax.set_title(title or "absolute position error (SE(2)-aligned)")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    _save(fig, path)


def plot_map_bev(
    path: str | Path,
    map_xyz: np.ndarray,
    trajectories_xy: Sequence[np.ndarray] = (),
    title: str = "static map (bird's-eye view)",
) -> None:
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8, 8))
    if len(map_xyz):
        ax.scatter(map_xyz[:, 0], map_xyz[:, 1], s=0.5, c="0.3", marker=".", linewidths=0)
    for xy in trajectories_xy:
        if len(xy):
            ax.plot(xy[:, 0], xy[:, 1], "-", lw=1.0)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    ax.set_title(f"{title}: {len(map_xyz)} points")
    _save(fig, path)
