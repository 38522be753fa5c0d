"""Graph insertion: sessions' odometry chains and verified loops into the pose graph."""

from __future__ import annotations

from typing import TYPE_CHECKING, Literal

import numpy as np

from radarslam.geometry import invert
from radarslam.io.loops import LoopCandidate, NodeKey
from radarslam.slam.state import Group, KeyFrame, MapState, Session

if TYPE_CHECKING:
    from radarslam.slam.pose_graph import PoseGraph


#: How a session's first pose enters the graph: on the tight prior, or on the weak one
#: (``pose_graph.unknown_anchor_sigmas``) of a session whose place is not known.
Anchor = Literal["prior", "unknown"]


class GraphInsertion:
    """Puts sessions, key frames and loops into ``graph``; every loop factor added is logged as
    accepted in ``state.loops`` and its information matrix kept in :attr:`loop_information`."""

    def __init__(self, state: MapState, graph: PoseGraph) -> None:
        self.state = state
        self.graph = graph
        #: Information matrix of every loop factor added, by (candidate, query).
        self.loop_information: dict[tuple[NodeKey, NodeKey], np.ndarray] = {}

    def add_node(self, session: Session, kf: KeyFrame) -> None:
        """The key frame's odometry factor to its predecessor (the first has none)."""
        if kf.key.index == 0:
            return
        # every key frame after a session's first has its motion (make_key_frame)
        assert kf.relative is not None and kf.relative_cov is not None
        self.graph.add_odometry(
            session.name, kf.key.index - 1, kf.key.index, kf.relative, kf.relative_cov
        )

    def add_loop(self, record: LoopCandidate, information: np.ndarray) -> None:
        self.graph.add_loop(
            record.candidate, record.query, record.candidate_from_query, information
        )
        self.loop_information[(record.candidate, record.query)] = information
        self.state.loops.append(record)

    def insert_session(
        self, session: Session, world_from_session: np.ndarray, anchor: Anchor
    ) -> None:
        """Put a session's odometry chain into the graph at ``world_from_session``. A session
        that continues another one's odometry goes on from that one's last key frame (inserted
        first if it is not yet), through the odometry's motion across the gap."""
        kfs = session.key_frames
        if session.inserted or not kfs:
            return
        first = kfs[0]
        if first.follows is not None:
            before = self.state.sessions[first.follows.session]
            if not before.inserted:
                group = self.state.groups[before.group]
                self.insert_session(before, group.from_session[before.name], anchor)
            anchor = "unknown"  # the chain places it; the weak prior only names its session
            assert first.relative is not None and first.relative_cov is not None
            world_from_first = self.graph.current_pose(first.follows) @ first.relative
            world_from_session = world_from_first @ invert(first.odometry_pose)
        self.graph.add_session(session.name, world_from_session @ first.odometry_pose, anchor)
        if first.follows is not None:
            assert first.relative is not None and first.relative_cov is not None
            self.graph.add_continuation(
                first.follows, first.key, first.relative, first.relative_cov
            )
        session.inserted = True
        session.world_from_session = world_from_session
        for kf in kfs[1:]:
            self.add_node(session, kf)

    def insert_group(self, group: Group, anchor: Anchor) -> None:
        """Put every session of a group into the graph (the first with ``anchor``) and its
        loops; a group outside the map becomes its own component."""
        for k, name in enumerate(group.from_session):
            self.insert_session(
                self.state.sessions[name],
                group.from_session[name],
                anchor if k == 0 else "unknown",
            )
        for p in group.loops:
            self.add_loop(p.record, p.information)
        group.loops = []
