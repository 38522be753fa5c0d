"""Session linking: verified loops between two groups of sessions are votes on where one lies
in the other; enough votes that agree merge the groups.

Each vote's placement puts the others' loop key frames within ``link_consistency_m``; once
``link_min_consistent_loops`` votes agree, the groups merge (the other votes are rejected as
false loops). A global registration that failed the tight-fitness or RMSE test by a little, if
well conditioned, is a weak vote: it counts only towards a link of ``weak_link_min_votes``
agreeing votes, one of them a full loop. A lone vote is checked where it predicts the session
lies: earlier (then later) key frames of its session, spaced apart, are registered from that
prediction, and enough of them accepted near it link the groups (``loops.confirm_*``; a street
driven the other way rarely gives two global matches). The merged placement is the mean of the
agreeing votes: each vote errs on its own.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np

from radarslam.geometry import invert, se2_to_matrix
from radarslam.io.loops import NodeKey
from radarslam.slam.insertion import GraphInsertion
from radarslam.slam.state import KeyFrame, MapState, PendingLoop, Session
from radarslam.slam.verification import Verification, se2_distance

if TYPE_CHECKING:
    from radarslam.slam.config import SlamConfig


def se2_mean(poses: list[np.ndarray]) -> np.ndarray:
    """Mean of nearby planar poses: mean translation, circular mean of the yaw."""
    t = np.mean([p[:2, 3] for p in poses], axis=0)
    yaws = np.array([np.arctan2(p[1, 0], p[0, 0]) for p in poses])
    yaw = float(np.arctan2(np.sin(yaws).mean(), np.cos(yaws).mean()))
    return se2_to_matrix(float(t[0]), float(t[1]), yaw)


@dataclass
class Confirmation:
    """A lone vote between two groups whose predicted placement is being checked at other key
    frames of its query's session (``loops.confirm_*``)."""

    vote: PendingLoop
    taken: list[np.ndarray]  # group-frame positions of the key frames used (the vote's first)
    confirmed: list[PendingLoop] = field(default_factory=list)
    checks: int = 0


class SessionLinker:
    """The votes between groups, the lone votes being confirmed, and the merges.

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
        self.confirming: list[Confirmation] = []
        #: Key frames that are the query of an accepted loop (a vote, in a group or in the map).
        self.closed: set[NodeKey] = set()

    # --- votes -----------------------------------------------------------------------------------

    def weak_vote(self, loop: PendingLoop) -> None:
        """A rejected global registration that counts towards a weak link."""
        rec = loop.record
        self.votes.append(loop)
        self.try_merge(self.state.group_of(rec.query), self.state.group_of(rec.candidate))

    def vote(self, session: Session, loop: PendingLoop) -> None:
        """An accepted loop between the query's group and another: the groups merge if enough
        votes agree, else a lone vote's placement is checked at other key frames."""
        a, b = session.group, self.state.group_of(loop.record.candidate)
        self.votes.append(loop)
        self.try_merge(a, b)
        if session.group != self.state.group_of(loop.record.candidate):
            self._confirm_vote(session, loop)

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

        # Each vote's key frame on side b, in b's frame: with ``at`` (side a), where it looked.
        at_b = [state.pose_in_group(self._side(v, b))[:2, 3] for v in votes]

        def independent(agree: list[int]) -> list[int]:
            """The agreeing votes that saw distinct places (full loops first): a vote counts
            only if, against every vote counted before it, its key frame lies
            ``link_vote_spacing_m`` away on at least one side."""
            counted: list[int] = []
            for j in sorted(agree, key=lambda j: (votes[j].weak, j)):
                if all(
                    max(np.hypot(*(at[j] - at[k])), np.hypot(*(at_b[j] - at_b[k])))
                    >= cfg.link_vote_spacing_m
                    for k in counted
                ):
                    counted.append(j)
            return counted

        def strength(agree: list[int]) -> tuple[int, int]:
            counted = independent(agree)
            return sum(not votes[j].weak for j in counted), len(counted)

        best: list[int] = []
        for i in range(len(votes)):
            agree = [j for j in range(len(votes)) if agree_on(i, j)]
            if strength(agree) > strength(best):
                best = agree
        counted = independent(best)
        strong = sum(not votes[j].weak for j in counted)
        weak_link = (
            cfg.weak_vote_min_tight_fitness is not None
            and strong >= 1
            and len(counted) >= cfg.weak_link_min_votes
        )
        if strong < cfg.link_min_consistent_loops and not weak_link:
            return
        if not any(
            votes[j].record.constraint_ratio >= cfg.link_min_constraint_ratio
            for j in counted
            if not votes[j].weak
        ):
            return
        b_from_a = se2_mean([placements[j] for j in best])  # each vote errs independently
        agreeing = {id(votes[j]) for j in best}
        links = []
        for v in votes:
            self.votes.remove(v)
            if id(v) in agreeing:
                if v.weak:  # loops.csv shows its tight fitness / RMSE past the thresholds
                    v = replace(v, record=replace(v.record, accepted=True, reason="ok"))
                links.append(v)
            elif v.weak:
                state.loops.append(v.record)
            else:
                state.loops.append(
                    replace(v.record, accepted=False, reason="inconsistent with the session link")
                )
        self._merge(a, b, b_from_a, links)

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

    # --- confirmations of lone votes --------------------------------------------------------------

    def _confirm_vote(self, session: Session, vote: PendingLoop) -> None:
        """A vote between two groups that linked nothing: check the placement it predicts at
        the session's earlier key frames now, and at its later ones as they come (see
        ``loops.confirm_*``)."""
        cfg = self.config.loops
        if not cfg.confirm_max_checks or cfg.proximity_radius_m is None:
            return
        if not vote.record.constraint_ratio >= cfg.confirm_min_constraint_ratio:
            return  # a slide along a straight street would be confirmed along it
        query = self.state.key_frame(vote.record.query)
        hyp = Confirmation(vote, taken=[self.state.pose_in_group(query)[:2, 3]])
        self.confirming.append(hyp)
        # Nearest in time first: the overlap that produced the vote extends around it.
        for kf in reversed(session.key_frames[: query.key.index]):
            if self._check(hyp, kf) is not None:
                break

    def confirm_with(self, kf: KeyFrame) -> None:
        """A new key frame checks the open confirmations of its session's lone votes."""
        for hyp in list(self.confirming):
            if hyp.vote.record.query.session == kf.key.session:
                self._check(hyp, kf)

    def _check(self, hyp: Confirmation, kf: KeyFrame) -> bool | None:
        """Register ``kf`` from the placement ``hyp``'s vote predicts, if it lies apart from
        the key frames already used and near the other group; then settle ``hyp`` when it can
        be: True (linked), False (given up), None (still open)."""
        cfg = self.config.loops
        state = self.state
        rec = hyp.vote.record
        a, b = state.group_of(rec.query), state.group_of(rec.candidate)
        if a == b:  # linked by other loops meanwhile; the catch-up searches these key frames
            return self._settle(hyp)
        pose_a = state.pose_in_group(kf)
        if min(np.hypot(*(pose_a[:2, 3] - xy)) for xy in hyp.taken) < cfg.confirm_spacing_m:
            return None
        pose_b = self._b_from_a(hyp.vote, a) @ pose_a
        found = state.near_key_frames(state.groups[b], pose_b[:2, 3])
        if not found:
            return None
        other = found[0][1]
        hyp.taken.append(pose_a[:2, 3])
        guess = invert(state.pose_in_group(other)) @ pose_b
        record, ver = self.verification.confirm(kf, other, guess)
        if record.accepted:
            hyp.confirmed.append(PendingLoop(record, ver.information))
        else:
            state.loops.append(record)
        hyp.checks += 1
        if len(hyp.confirmed) >= cfg.confirm_min_loops or hyp.checks == cfg.confirm_max_checks:
            return self._settle(hyp)
        return None

    def _settle(self, hyp: Confirmation) -> bool:
        """Close a confirmation: with enough loops they join the votes and the groups link
        (True); otherwise, or when other loops linked the groups meanwhile, they are logged as
        rejected (False)."""
        cfg = self.config.loops
        state = self.state
        self.confirming.remove(hyp)
        rec = hyp.vote.record

        def linked() -> bool:
            return state.group_of(rec.query) == state.group_of(rec.candidate)

        reason = "the sessions were linked by other loops meanwhile"
        if not linked():
            reason = (
                f"{len(hyp.confirmed)} of {hyp.checks} confirmations of a link vote "
                f"(need {cfg.confirm_min_loops} that agree)"
            )
            if len(hyp.confirmed) >= cfg.confirm_min_loops:
                self.votes.extend(hyp.confirmed)
                # before the merge: its catch-up need not search these key frames again
                closing = {p.record.query for p in hyp.confirmed} - self.closed
                self.closed |= closing
                self.try_merge(state.group_of(rec.query), state.group_of(rec.candidate))
                if linked():
                    return True
                self.closed -= closing
                for p in hyp.confirmed:  # they disagreed with the vote after all
                    self.votes.remove(p)
                reason = "the confirmations disagree with the vote"
        for p in hyp.confirmed:
            state.loops.append(replace(p.record, accepted=False, reason=reason))
        return False

    # --- ends ------------------------------------------------------------------------------------

    def settle_open(self) -> None:
        """Close every open confirmation: its session gets no more key frames."""
        for hyp in list(self.confirming):
            self._settle(hyp)

    def finish(self) -> None:
        """At the end of the run: open confirmations closed, votes that never linked anything
        logged as rejected."""
        self.settle_open()
        for vote in self.votes:  # never confirmed by a consistent second loop
            if vote.weak:  # rejected by verification all along
                self.state.loops.append(vote.record)
                continue
            self.state.loops.append(
                replace(
                    vote.record,
                    accepted=False,
                    reason="too few consistent loops to link the session",
                )
            )
        self.votes = []
