"""Session linking: verified loops between two groups of sessions are votes on where one lies
in the other; enough votes that agree merge the groups.

Each vote's placement puts the others' loop key frames within ``link_consistency_m``; once
``link_min_consistent_loops`` votes agree, the groups merge (the other votes are rejected as
false loops).
The merged placement is the mean of the agreeing votes: each vote errs on its own. A placement
that would put two scenes of one log (one vehicle's drive) farther apart than the vehicle could
have driven between them is not a candidate (``same_log_max_speed_mps``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from radarslam.geometry import invert, se2_to_matrix
from radarslam.io.loops import NodeKey
from radarslam.slam.insertion import GraphInsertion
from radarslam.slam.state import KeyFrame, MapState, PendingLoop, Session
from radarslam.slam.verification import Verification, se2_distance

if TYPE_CHECKING:
    from radarslam.slam.config import SlamConfig


#: Odometry drift allowed on top of the drivable distance between two scenes of one log.
_SAME_LOG_DRIFT_M = 20.0


def se2_mean(poses: list[np.ndarray]) -> np.ndarray:
    """Mean of nearby planar poses: mean translation, circular mean of the yaw."""
    t = np.mean([p[:2, 3] for p in poses], axis=0)
    yaws = np.array([np.arctan2(p[1, 0], p[0, 0]) for p in poses])
    yaw = float(np.arctan2(np.sin(yaws).mean(), np.cos(yaws).mean()))
    return se2_to_matrix(float(t[0]), float(t[1]), yaw)


class SessionLinker:
    """The votes between groups and the merges.

    The group of the anchored session is the map: a group that merges into it enters the graph
    (through ``insertion``) with its poses moved there, together with the loops found inside
    it. After a merge ``catch_up(moved, stayed)`` runs: the key frames processed before the link
    (which had no prediction then) look for their revisits on the other side."""

    def __init__(
        self,
        config: SlamConfig,
        state: MapState,
        verification: Verification,
        insertion: GraphInsertion,
        catch_up: Callable[[list[str], list[str]], None],
    ) -> None:
        self.config = config
        self.state = state
        self.verification = verification
        self.insertion = insertion
        self.catch_up = catch_up
        #: Verified loops between two groups, waiting for a consistent partner to merge them.
        self.votes: list[PendingLoop] = []
        #: Key frames that are the query of an accepted loop (a vote, in a group or in the map).
        self.closed: set[NodeKey] = set()

    # --- votes -----------------------------------------------------------------------------------

    def vote(self, session: Session, loop: PendingLoop) -> None:
        """An accepted loop between the query's group and another: the groups merge if enough
        votes agree."""
        self.votes.append(loop)
        self.try_merge(session.group, self.state.group_of(loop.record.candidate))

    def _b_from_a(self, vote: PendingLoop, a: int) -> np.ndarray:
        """Where a vote between groups ``a`` and another puts ``a`` in the other's frame."""
        rec, state = vote.record, self.state
        q, c = state.key_frame(rec.query), state.key_frame(rec.candidate)
        other_from_query_group = (
            state.pose_in_group(c) @ rec.candidate_from_query @ invert(state.pose_in_group(q))
        )
        if state.group_of(rec.query) == a:
            return other_from_query_group
        return invert(other_from_query_group)

    def _side(self, vote: PendingLoop, group: int) -> KeyFrame:
        """The key frame of a vote between two groups that lies in ``group``."""
        rec = vote.record
        key = rec.query if self.state.group_of(rec.query) == group else rec.candidate
        return self.state.key_frame(key)

    def try_merge(self, a: int, b: int) -> None:
        """Merge groups ``a`` and ``b`` once enough votes between them agree on their relative
        placement (the largest consistent set wins; the others are rejected as false loops)."""
        cfg = self.config.loops
        state = self.state
        groups_of = {a, b}
        votes = [
            v
            for v in self.votes
            if {state.group_of(v.record.query), state.group_of(v.record.candidate)} == groups_of
        ]
        placements = [self._b_from_a(v, a) for v in votes]
        # Where each vote's key frame on side a lies in a's frame: two placements are compared
        # where the loops are, not at a's origin, which may be hundreds of metres away (a
        # 0.5 deg difference there is metres of translation, and it would hide a slide along a
        # street of the same size).
        at = [state.pose_in_group(self._side(v, a))[:2, 3] for v in votes]

        def agree_on(i: int, j: int) -> bool:
            t_i, t_j = placements[i], placements[j]
            moved = max(
                float(np.hypot(*((t_i[:2, :2] - t_j[:2, :2]) @ x + t_i[:2, 3] - t_j[:2, 3])))
                for x in (at[i], at[j])
            )
            dyaw = abs(se2_distance(t_i, t_j)[1])
            return moved <= cfg.link_consistency_m and dyaw <= cfg.link_consistency_deg

        best: list[int] = []
        best_count = 0
        b_from_a = np.eye(4)
        for i in range(len(votes)):
            agree = [j for j in range(len(votes)) if agree_on(i, j)]
            count = len(agree)
            if count <= best_count:
                continue
            placement = se2_mean([placements[j] for j in agree])  # each vote errs on its own
            if self._drivable(a, b, placement):
                best, best_count, b_from_a = agree, count, placement
        if len(best) < cfg.link_min_consistent_loops:
            return
        agreeing = {id(votes[j]) for j in best}
        links = []
        for v in votes:
            self.votes.remove(v)
            if id(v) in agreeing:
                links.append(v)
            else:
                state.loops.append(
                    replace(v.record, accepted=False, reason="inconsistent with the session link")
                )
        self._merge(a, b, b_from_a, links)

    def _drivable(self, a: int, b: int, b_from_a: np.ndarray) -> bool:
        """Whether placing group ``a`` at ``b_from_a`` in ``b`` keeps every pair of scenes of
        one log (one in each group) within reach of each other: the later one's first key frame
        no farther from the earlier one's last than ``same_log_max_speed_mps`` times the time
        between them, plus ``_SAME_LOG_DRIFT_M``."""
        max_speed = self.config.loops.same_log_max_speed_mps
        if max_speed is None:
            return True
        state = self.state

        def in_b(session: Session, kf: KeyFrame) -> np.ndarray:
            pose = state.pose_in_group(kf)
            return b_from_a @ pose if session.group == a else pose

        for name_a in state.groups[a].from_session:
            for name_b in state.groups[b].from_session:
                sa, sb = state.sessions[name_a], state.sessions[name_b]
                if not sa.log or sa.log != sb.log or not sa.key_frames or not sb.key_frames:
                    continue
                first, second = sorted((sa, sb), key=lambda s: s.timestamps_us[0])
                gap_us = second.timestamps_us[0] - first.timestamps_us[-1]
                if gap_us < 0:
                    continue  # overlapping in time: not one drive's consecutive scenes
                end = in_b(first, first.key_frames[-1])
                start = in_b(second, second.key_frames[0])
                reach_m = max_speed * gap_us * 1e-6 + _SAME_LOG_DRIFT_M
                if np.hypot(*(end[:2, 3] - start[:2, 3])) > reach_m:
                    return False
        return True

    def _merge(self, a: int, b: int, b_from_a: np.ndarray, links: list[PendingLoop]) -> None:
        state = self.state
        ga, gb = state.groups[a], state.groups[b]
        if ga.in_map or (not gb.in_map and len(ga.from_session) > len(gb.from_session)):
            ga, gb, b_from_a = gb, ga, invert(b_from_a)  # keep the map's (or larger) frame
        del state.groups[ga.index]
        moved = list(ga.from_session)
        for name, group_from_session in ga.from_session.items():
            gb.from_session[name] = b_from_a @ group_from_session
            state.sessions[name].group = gb.index
        loops = ga.loops + links
        stayed = [n for n in gb.from_session if n not in ga.from_session]
        if gb.in_map:
            for name in moved:
                self.insertion.insert_session(
                    state.sessions[name], gb.from_session[name], "unknown"
                )
            for p in loops:
                self.insertion.add_loop(p.record, p.information)
        else:
            gb.loops.extend(loops)
        self.catch_up(moved, stayed)

    # --- ends ------------------------------------------------------------------------------------

    def finish(self) -> None:
        """At the end of the run: votes that never linked anything logged as rejected."""
        for vote in self.votes:  # never joined by a consistent second loop
            self.state.loops.append(
                replace(
                    vote.record,
                    accepted=False,
                    reason="too few consistent loops to link the session",
                )
            )
        self.votes = []
