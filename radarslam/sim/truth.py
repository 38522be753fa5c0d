"""The simulator's ground truth at the radars' true measurement times.

A synthetic dataroot writes each ego pose at its radar stamp, as nuScenes does, and the stamps
of a log are offset from the true measurement times by the log's clock offset
(``radar.clock_offset_mean_s``, docs/sim.md). An evaluation against the written poses therefore
includes an along-track error no radar-only method can remove; evaluated against the poses at
the true measurement times it shows what the method itself gets wrong. This reads the truth the
simulator keeps (``synthetic/summary.json`` and the per-log ``synthetic/logs/<log>.npz``).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from radarslam.errors import DataError
from radarslam.nuscenes.json_stream import _field, _load_json_list


class MeasurementTimeTruth:
    """Ground-truth poses of a synthetic dataroot at the true measurement time of a radar
    stamp: ``poses(scene, stamps_us)``."""

    def __init__(self, dataroot: str | Path, version: str) -> None:
        root = Path(dataroot)
        summary_path = root / "synthetic" / "summary.json"
        if not summary_path.is_file():
            raise DataError(f"{summary_path}: missing (not a synthetic dataroot)")
        summary = json.loads(summary_path.read_text())
        self._offset_s = {
            str(log["log"]): float(log.get("clock_offset_s", 0.0))
            for log in summary.get("per_log", [])
        }
        # The reader's checked table loads: a missing or corrupt table is one line.
        log_path, scene_path = root / version / "log.json", root / version / "scene.json"
        log_name = {
            _field(log_path, r, "token"): _field(log_path, r, "logfile")
            for r in _load_json_list(log_path)
        }
        self._log_of = {
            _field(scene_path, r, "name"): log_name.get(_field(scene_path, r, "log_token"), "")
            for r in _load_json_list(scene_path)
        }
        self._root = root
        self._tracks: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}

    def clock_offset_s(self, scene: str) -> float:
        """The scene's log: written stamp minus true measurement time."""
        return self._offset_s.get(self._log(scene), 0.0)

    def _log(self, scene: str) -> str:
        if not self._log_of.get(scene):
            raise DataError(f"scene {scene!r}: not in {self._root} (or its log is not)")
        return self._log_of[scene]

    def _track(self, log: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if log not in self._tracks:
            path = self._root / "synthetic" / "logs" / f"{log}.npz"
            if not path.is_file():
                raise DataError(f"{path}: missing (the simulator's truth of log {log})")
            with np.load(path) as z:
                t = np.asarray(z["gt_time_us"], dtype=np.float64)
                xy = np.asarray(z["gt_xy"], dtype=np.float64)
                yaw = np.unwrap(np.asarray(z["gt_yaw"], dtype=np.float64))
            self._tracks[log] = (t, xy, yaw)
        return self._tracks[log]

    def poses(self, scene: str, stamps_us: np.ndarray) -> np.ndarray:
        """(N, 4, 4) ``world_from_ego`` at each stamp's true measurement time."""
        log = self._log(scene)
        t, xy, yaw = self._track(log)
        when = np.asarray(stamps_us, dtype=np.float64) - self._offset_s.get(log, 0.0) * 1e6
        if len(when) and (when.min() < t[0] or when.max() > t[-1]):
            raise DataError(f"scene {scene!r}: stamps outside its log's ground-truth track")
        x, y = np.interp(when, t, xy[:, 0]), np.interp(when, t, xy[:, 1])
        a = np.interp(when, t, yaw)
        out = np.tile(np.eye(4), (len(when), 1, 1))
        out[:, 0, 0], out[:, 0, 1], out[:, 1, 0], out[:, 1, 1] = (
            np.cos(a),
            -np.sin(a),
            np.sin(a),
            np.cos(a),
        )
        out[:, 0, 3], out[:, 1, 3] = x, y
        return out
