"""Loop-candidate proposers: where a key frame may have been before.

Every proposer answers :meth:`CandidateProposer.propose` with the candidates the key frame is to
be verified against, in order; the pipeline asks them in turn (recognition, turned,
proximity), telling each whether an earlier one closed a loop already, and reports back to each
whether one of its own candidates was accepted (:meth:`CandidateProposer.settle`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Protocol

import numpy as np

from radarslam.io.loops import NodeKey
from radarslam.slam.state import KeyFrame, MapState, Session
from radarslam.types import AccumulatedCloud

if TYPE_CHECKING:
    from radarslam.slam.config import SlamConfig
    from radarslam.slam.result import SlamTimings

#: A half turn about the z axis.
HALF_TURN = np.diag([-1.0, -1.0, 1.0, 1.0])


def turned_cloud(cloud: AccumulatedCloud) -> AccumulatedCloud:
    """The cloud turned by 180 deg about its reference sensor: roughly what the sensor sees of
    the same place when the street is driven the other way round (the far field, which only the
    forward radar reaches, stays on the wrong side). Its sample token gets a ``#turned`` suffix
    so that a recognizer's per-token feature cache keeps the two apart."""
    points = cloud.points.copy()
    fields = points.dtype.names or ()
    for name in ("x", "y", "vx", "vy", "vx_comp", "vy_comp"):
        if name in fields:
            points[name] = -points[name]
    return replace(
        cloud,
        points=points,
        world_from_ref=cloud.world_from_ref @ HALF_TURN,
        sample_token=f"{cloud.sample_token}#turned" if cloud.sample_token else "",
    )


@dataclass(frozen=True)
class Proposal:
    """A candidate key frame for a loop with the query, and how to verify it."""

    candidate: KeyFrame
    distance: float  # descriptor distance (NaN: not from a descriptor)
    source: str  # the ``source`` column of loops.csv
    #: a field of :class:`~radarslam.slam.verification.Verifiers` (None: the global search, or
    #: the guided one where odometry or the map predicts the pose)
    verifier: str | None = None
    hint: np.ndarray | None = None  # where the search starts without a prediction

    @property
    def search(self) -> str:
        """The kind of registration search it gets: ``global``, ``turned`` or ``proximity``
        (a candidate proposed twice in one key frame is verified once per kind)."""
        if self.verifier in ("turned", "merge_turned"):
            return "turned"
        return "proximity" if self.verifier == "proximity" else "global"


class CandidateProposer(Protocol):
    def propose(
        self, session: Session, kf: KeyFrame, cloud: AccumulatedCloud, closed: bool
    ) -> list[Proposal]:
        """Candidates for the session's newest key frame ``kf`` (``cloud``: its accumulated
        cloud); ``closed``: an earlier proposer's candidate was accepted."""
        ...

    def settle(self, session: Session, kf: KeyFrame, accepted: bool) -> None:
        """Whether one of the candidates just proposed for ``kf`` was accepted."""
        ...


class _AutoPlaceProposer:
    """What the AutoPlace proposers share: the run's state, the (lazily loaded) recognizer, the
    timings their descriptor time is booked to, and the turned query."""

    def __init__(
        self, config: SlamConfig, state: MapState, recognizer: Callable, timings: SlamTimings
    ) -> None:
        self.config, self.state, self.recognizer, self.timings = config, state, recognizer, timings

    def settle(self, session, kf, accepted):
        pass

    def turned_proposals(
        self, sequence: list[AccumulatedCloud], exclude: Callable, source: str, verifier: str
    ) -> list[Proposal]:
        """The best match of the sequence turned by 180 deg (a street driven the other way
        round), for the search over headings near a half turn."""
        rec = self.recognizer()
        desc, rcs = rec.describe([turned_cloud(c) for c in sequence])
        return [
            Proposal(
                self.state.key_frame(c.key),
                c.descriptor_distance,
                source,
                verifier=verifier,
                hint=HALF_TURN,
            )
            for c in rec.query_descriptor(desc, rcs, k=1, exclude=exclude)
        ]


class RecognitionProposer(_AutoPlaceProposer):
    """AutoPlace: the descriptor of the last key frames (t-2, t-1, t) queried among earlier key
    frames, the recent past of the same session excluded; the key frame is then added. The
    recognizer encodes each key frame's image once (its feature cache is keyed by sample
    token)."""

    def propose(self, session, kf, cloud, closed):
        cfg = self.config.loops
        rec = self.recognizer()
        t0 = time.perf_counter()
        desc, rcs = rec.describe(self.state.sequence(session, cloud, rec.seq_len))
        candidates = []
        if kf.key.index - session.last_loop_kf > cfg.min_key_frames_between_loops:
            candidates = rec.query_descriptor(
                desc, rcs, k=cfg.num_candidates, exclude=self.state.excluded(kf)
            )
        rec.add_descriptor(desc, rcs, kf.key)
        self.timings.place_recognition_s += time.perf_counter() - t0
        budget = None if session.inserted else cfg.unlinked_candidates_per_key_frame
        proposals = []
        for cand in candidates:
            gate = cfg.max_descriptor_distance
            if gate is not None and cand.descriptor_distance > gate:
                continue
            if budget is not None:
                if budget == 0:
                    break
                budget -= 1
            proposals.append(
                Proposal(self.state.key_frame(cand.key), cand.descriptor_distance, "recognition")
            )
        return proposals


class TurnedProposer(_AutoPlaceProposer):
    """For a session outside the map when nothing closed the key frame yet: AutoPlace queried
    with the key frame's image sequence turned by 180 deg, i.e. as the street looks driven the
    other way round, against the key frames of sessions not linked to it yet; the best match is
    verified by the translation search over headings near 180 deg (``loops.reversed_search``).
    It searches every ``reversed_every``-th key frame."""

    def propose(self, session, kf, cloud, closed):
        cfg = self.config.loops
        if closed or not cfg.reversed_search:
            return []
        if (
            self.state.groups[session.group].in_map
            or kf.key.index < self.config.key_frames.local_map_neighbors
            or kf.key.index - session.last_reversed_kf < cfg.reversed_every
            or kf.key.index - session.last_loop_kf <= cfg.min_key_frames_between_loops
        ):
            return []
        session.last_reversed_kf = kf.key.index
        t0 = time.perf_counter()
        rec = self.recognizer()
        sequence = self.state.sequence(session, cloud, rec.seq_len)
        sessions = self.state.sessions
        group = session.group

        def exclude(key: NodeKey) -> bool:
            return sessions[key.session].group == group

        proposals = self.turned_proposals(sequence, exclude, "reversed", "turned")
        self.timings.place_recognition_s += time.perf_counter() - t0
        return proposals


class MergeProposer(_AutoPlaceProposer):
    """Map merging (``loops.merge_search_every``): every N-th key frame of a session, while
    other groups exist, AutoPlace queried among the key frames of the other groups only, plain
    and turned by 180 deg (``loops.reversed_search``), whatever closed the key frame in its own
    group. The best match of each query goes to the global search; accepted, it is a vote
    between the two groups (:class:`~radarslam.slam.linking.SessionLinker`)."""

    def propose(self, session, kf, cloud, closed):
        cfg = self.config.loops
        every = cfg.merge_search_every
        if (
            every is None
            or len(self.state.groups) < 2
            or kf.key.index < self.config.key_frames.local_map_neighbors
            or kf.key.index - session.last_merge_kf < every
        ):
            return []
        session.last_merge_kf = kf.key.index
        t0 = time.perf_counter()
        rec = self.recognizer()
        sessions, group = self.state.sessions, session.group
        recent = self.state.excluded(kf)

        def exclude(key: NodeKey) -> bool:
            return sessions[key.session].group == group or recent(key)

        # the recognizer caches each image's features: only the turned ones are new
        sequence = self.state.sequence(session, cloud, rec.seq_len)
        desc, rcs = rec.describe(sequence)
        proposals = [
            Proposal(self.state.key_frame(c.key), c.descriptor_distance, "merge", verifier="merge")
            for c in rec.query_descriptor(desc, rcs, k=1, exclude=exclude)
            if cfg.max_descriptor_distance is None
            or c.descriptor_distance <= cfg.max_descriptor_distance
        ]
        if cfg.reversed_search:
            proposals += self.turned_proposals(sequence, exclude, "merge-reversed", "merge_turned")
        self.timings.place_recognition_s += time.perf_counter() - t0
        return proposals


class ProximityProposer:
    """When nothing else closed the key frame: the nearest key frames of its group within
    ``loops.proximity_radius_m`` of its predicted position, registered from that prediction
    (ICP only). Once a session is linked, this closes a loop at nearly every revisiting key
    frame, which is what pulls the whole session onto the map."""

    def __init__(
        self, config: SlamConfig, state: MapState, placed: Callable[[KeyFrame], np.ndarray]
    ) -> None:
        self.config, self.state, self.placed = config, state, placed

    def candidates(
        self, session: Session, kf: KeyFrame, among: set[str] | None = None
    ) -> list[Proposal]:
        """Key frames of the query's group (of its sessions ``among``, if given) near the
        query's predicted position, nearest first, at most one per session (the query's own
        recent past excluded)."""
        cfg = self.config.loops
        if cfg.proximity_radius_m is None:
            return []
        group = self.state.groups[session.group]
        # Candidates and query are placed the same way (link @ odometry; the query possibly
        # through its latest loop, ``placed``) so that a common error of the placements cancels;
        # the verification's guess then uses the graph's estimate.
        query_xy = self.placed(kf)[:2, 3]
        found = self.state.near_key_frames(group, query_xy, among, recent_of=kf)
        return [
            Proposal(k, float("nan"), "proximity", verifier="proximity")
            for _, k in found[: cfg.proximity_candidates]
        ]

    def propose(self, session, kf, cloud, closed):
        return [] if closed else self.candidates(session, kf)

    def settle(self, session, kf, accepted):
        pass
