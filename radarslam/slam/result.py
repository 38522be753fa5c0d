"""What a SLAM run returns: the optimised sessions, every loop candidate, the graph's
components, the static map and the timings."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from radarslam.io.loops import LoopCandidate
from radarslam.slam.map import StaticMap


@dataclass
class SlamTimings:
    frames: int = 0
    key_frames: int = 0
    data_s: float = 0.0
    odometry_s: float = 0.0
    key_frame_s: float = 0.0  # accumulating the key-frame clouds (odometry side)
    place_recognition_s: float = 0.0
    verification_s: float = 0.0
    backend_s: float = 0.0
    final_optimization_s: float = 0.0
    calibration_pass_s: float = 0.0  # fusion.calibration.passes: 2, before the run proper
    isam2_update_ms: list[float] = field(default_factory=list)

    @property
    def total_s(self) -> float:
        return (
            self.data_s
            + self.odometry_s
            + self.key_frame_s
            + self.place_recognition_s
            + self.verification_s
            + self.backend_s
            + self.final_optimization_s
            + self.calibration_pass_s
        )


@dataclass
class SlamResult:
    sessions: list  # list[radarslam.slam.outputs.SessionResult]
    loops: list[LoopCandidate]
    components: list  # list[radarslam.slam.pose_graph.GraphComponent]
    static_map: StaticMap | None
    timings: SlamTimings
    duration_s: float  # sensor time covered by the run
    graph: object = None  # the PoseGraph, for marginals / g2o export
    #: The odometry's Doppler calibration over the run (``summary.json``: mounting yaws per radar
    #: with their sigmas; with a calibration pass, what it applied plus what was left)
    doppler_calibration: dict | None = None
    #: Every radar rig's calibration when the scenes come from several vehicles (else empty).
    doppler_calibrations_by_rig: list[dict] = field(default_factory=list)
    #: session -> the session whose drive it continues (``SlamConfig.continue_log_scenes``)
    continues: dict[str, str] = field(default_factory=dict)

    @property
    def accepted_loops(self) -> list[LoopCandidate]:
        return [c for c in self.loops if c.accepted]


def assemble_result(
    state,
    graph,
    static_map_config,
    timings: SlamTimings,
    duration_s: float,
    doppler_calibration: dict | None = None,
    doppler_calibrations_by_rig: list[dict] | None = None,
):
    """The :class:`SlamResult` of an optimised graph: each session's key-frame poses (SLAM,
    odometry, ground truth) and the static map built from the SLAM poses."""
    from radarslam.slam.map import StaticMapBuilder
    from radarslam.slam.outputs import SessionResult

    estimate = graph.estimate()
    sessions = []
    builder = StaticMapBuilder(static_map_config)
    for s in state.sessions.values():
        if not s.key_frames:
            continue
        slam = np.stack([estimate[kf.key] for kf in s.key_frames])
        sessions.append(
            SessionResult(
                name=s.name,
                timestamps_us=np.array([kf.timestamp_us for kf in s.key_frames], np.int64),
                slam_poses=slam,
                odometry_poses=np.stack([kf.odometry_pose for kf in s.key_frames]),
                gt_poses=np.stack([kf.gt_pose for kf in s.key_frames]),
            )
        )
        for kf, pose in zip(s.key_frames, slam, strict=True):
            builder.add(pose @ kf.ego_from_ref, kf.cloud_points)
    has_points = any(len(kf.cloud_points) for kf in state.all_key_frames())
    static_map = builder.build() if has_points else None
    return SlamResult(
        sessions=sessions,
        loops=list(state.loops),
        components=graph.components(),
        static_map=static_map,
        timings=timings,
        duration_s=duration_s,
        graph=graph,
        doppler_calibration=doppler_calibration,
        doppler_calibrations_by_rig=list(doppler_calibrations_by_rig or []),
        continues={s.name: s.continues for s in state.sessions.values() if s.continues is not None},
    )
