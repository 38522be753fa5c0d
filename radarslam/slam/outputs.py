"""Writing a SLAM results folder (layout and the files it shares with an odometry folder:
:mod:`radarslam.io.results`, docs/outputs.md), every file atomically.

::

    RESULTS_DIR/
      run.json                      format tag, kind "slam", the session order (processing order)
      poses_<session>.tum / .kitti  SLAM estimate per key frame (world_from_ego)
      odometry_<session>.tum/.kitti odometry-only estimate, same key frames
      gt_<session>.tum / .kitti     ground truth at the same timestamps
      loops.csv                     every loop candidate, accepted or rejected, with the reason
      map.ply                       static map (binary PLY, as open3d writes it)
      plots/map_bev.png             the map in bird's-eye view
      pose_graph.g2o                (optional) the final graph
      metrics.json, plots/*.png     written by ``radarslam eval RESULTS_DIR``

:func:`write_results` writes the folder as a whole
(:func:`radarslam.io.results.write_results_folder`): a reader never sees a partial folder (an
interrupted run leaves the previous one) and a re-run leaves no file of the previous run behind.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from radarslam.io.atomic import write_text_atomic
from radarslam.io.loops import LoopCandidate, write_loops_csv
from radarslam.io.ply import write_ply_points
from radarslam.io.results import check_results_dir, write_results_folder, write_trajectories
from radarslam.slam.map import StaticMap

__all__ = [
    "SessionResult",
    "check_results_dir",
    "write_map_ply",
    "write_results",
    "write_session",
]


@dataclass(frozen=True)
class SessionResult:
    """One session's key-frame trajectories, row i = key frame i (``NodeKey.index``)."""

    name: str
    timestamps_us: np.ndarray  # (N,) int64
    slam_poses: np.ndarray  # (N, 4, 4)
    odometry_poses: np.ndarray | None = None
    gt_poses: np.ndarray | None = None


def write_session(results_dir: str | Path, result: SessionResult) -> None:
    write_trajectories(
        results_dir,
        result.name,
        result.timestamps_us,
        {"slam": result.slam_poses, "odometry": result.odometry_poses, "gt": result.gt_poses},
    )


def write_map_ply(path: str | Path, static_map: StaticMap) -> None:
    """The static map as binary PLY (points; colours encode RCS when known)."""
    xyz = np.asarray(static_map.xyz, float)
    colors = None
    rcs = np.asarray(static_map.rcs, dtype=np.float64)
    if len(rcs) and np.any(np.isfinite(rcs)):
        lo, hi = np.nanpercentile(rcs, [2, 98])
        v = np.clip((np.nan_to_num(rcs, nan=lo) - lo) / max(hi - lo, 1e-9), 0, 1)
        colors = np.column_stack([v, 0.5 * np.ones_like(v), 1 - v])
    write_ply_points(path, xyz, colors)


def write_results(
    results_dir: str | Path,
    sessions: Sequence[SessionResult],
    loops: Sequence[LoopCandidate] | None = None,
    static_map: StaticMap | None = None,
    config_yaml: str | None = None,
    plots: bool = True,
    components: Sequence[Sequence[str]] | None = None,
    extra_json: Mapping[str, object] | None = None,
    finish: Callable[[Path], None] | None = None,
    continues: Mapping[str, str] | None = None,
) -> Path:
    """Write everything a run produced; ``radarslam eval`` reads it back.

    The folder is written as a whole (see the module docstring): an existing ``results_dir`` is
    replaced, and only when it is a results folder (:func:`check_results_dir`). ``extra_json``:
    more files, name -> JSON object (e.g. ``timing.json``). ``finish(folder)`` runs last on the
    folder before it replaces ``results_dir`` (``radarslam run`` evaluates it there, so that an
    interrupted evaluation leaves the previous folder, not a new one without its metrics).
    """

    def contents(d: Path) -> None:
        _write_contents(d, sessions, loops, static_map, config_yaml, plots)

    return write_results_folder(
        results_dir,
        [s.name for s in sessions],
        "slam",
        contents,
        components=components,
        continues=continues,
        extra_json=extra_json,
        finish=finish,
    )


def _write_contents(d, sessions, loops, static_map, config_yaml, plots) -> None:
    for s in sessions:
        write_session(d, s)
    if loops is not None:
        write_loops_csv(d / "loops.csv", list(loops))
    if static_map is not None:
        write_map_ply(d / "map.ply", static_map)
        if plots:
            from radarslam.eval.plots import plot_map_bev

            plot_map_bev(
                d / "plots" / "map_bev.png",
                static_map.xyz,
                [np.asarray(s.slam_poses)[:, :2, 3] for s in sessions],
            )
    if config_yaml is not None:
        write_text_atomic(d / "config.yaml", config_yaml)
