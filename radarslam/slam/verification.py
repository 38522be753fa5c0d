"""Verification of loop candidates: which :class:`~radarslam.slam.loop_closure.LoopVerifier`
variant registers a candidate, from which prediction, and the checks of its result against
that prediction."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from radarslam.geometry import invert, wrap_angle
from radarslam.io.loops import LoopCandidate, LoopVerification
from radarslam.slam.state import KeyFrame, MapState

if TYPE_CHECKING:
    from radarslam.slam.config import SlamConfig


def se2_distance(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """(metres, degrees) between two planar poses."""
    d = invert(a) @ b
    return float(np.hypot(d[0, 3], d[1, 3])), float(
        abs(np.degrees(wrap_angle(np.arctan2(d[1, 0], d[0, 0]))))
    )


@dataclass
class Verifiers:
    """The verifier variants, one per kind of prediction a candidate comes with."""

    #: no prediction: the global search over headings and translations
    recognition: object
    #: predicted by odometry or the map: a local search around the prediction
    guided: object
    #: proximity candidates, predicted by the map to a metre or two: ICP from the prediction
    proximity: object
    #: turned-image candidates: the global search over headings near a half turn
    turned: object
    #: the merge search's candidates (``recognition`` and ``turned`` at the merge search's own
    #: ``min_tight_fitness``): it always finds a best match among the other groups, whether
    #: they hold the place or not
    merge: object
    merge_turned: object

    @classmethod
    def from_config(cls, cfg) -> Verifiers:
        from radarslam.slam.loop_closure import LoopVerifier

        lv = cfg.backend.loop_verification
        guided = lv.model_copy(
            update={
                "heading_step_deg": 360.0,  # one hypothesis: the predicted heading
                "search_radius_m": cfg.loops.guided_search_radius_m,
                "refine_top_k": 1,
            }
        )
        # Proximity candidates come with the map's prediction, good to a metre or two: ICP from
        # it alone, no search over headings and translations.
        proximity = lv.model_copy(
            update={
                "heading_step_deg": 360.0,
                "correlative_search": False,
                "refine_top_k": 1,
                "max_range_m": cfg.loops.proximity_max_range_m,
                "min_tight_fitness": cfg.loops.proximity_min_tight_fitness,
            }
        )
        # Turned-image candidates come with a rough relative heading (half a turn) but no
        # position: the global translation search, over headings near 180 deg only.
        turned = lv.model_copy(
            update={"heading_range_deg": cfg.loops.reversed_heading_range_deg, "refine_top_k": 1}
        )
        tight = {"min_tight_fitness": cfg.loops.merge_min_tight_fitness}
        return cls(
            recognition=LoopVerifier(lv),
            guided=LoopVerifier(guided),
            proximity=LoopVerifier(proximity),
            turned=LoopVerifier(turned),
            merge=LoopVerifier(lv.model_copy(update=tight)),
            merge_turned=LoopVerifier(turned.model_copy(update=tight)),
        )


class Verification:
    """Registers a query key frame's local map against a candidate's, from the best prediction
    there is: odometry inside a session, the group's placement (or its latest loop) across
    sessions of one group, none across groups."""

    def __init__(self, config: SlamConfig, state: MapState, verifiers: Verifiers) -> None:
        self.config = config
        self.state = state
        self.verifiers = verifiers
        # (query session, candidate session or None: any) -> the latest loop inside one group
        self._last_loop: dict[tuple[str, str | None], LoopCandidate] = {}

    def note_loop(self, record: LoopCandidate) -> None:
        """An accepted loop between two sessions of one group: later guesses outside the map
        chain from it."""
        self._last_loop[(record.query.session, record.candidate.session)] = record
        self._last_loop[(record.query.session, None)] = record

    def guess(self, query: KeyFrame, cand: KeyFrame) -> np.ndarray | None:
        """The predicted candidate_from_query (None: nothing predicts it)."""
        state = self.state
        qs, cs = state.sessions[query.key.session], state.sessions[cand.key.session]
        if qs is cs:
            return invert(cand.odometry_pose) @ query.odometry_pose
        if qs.group != cs.group:
            return None
        last = self._last_loop.get((qs.name, cs.name)) or self._last_loop.get((qs.name, None))
        if not qs.inserted and last is not None:
            # Outside the map no graph corrects the placements, and both odometry chains drift
            # from where the sessions were linked: chain from the query session's latest loop
            # (with the candidate's session if there is one) over a short span of odometry.
            return invert(state.pose_in_group(cand)) @ self._chained(query, last)
        return invert(state.pose_in_group(cand)) @ state.pose_in_group(query)

    def _chained(self, query: KeyFrame, loop: LoopCandidate) -> np.ndarray:
        """group_from_query through ``loop`` (of the query's session): the loop's candidate
        placed by link @ odometry, the loop's measurement, then the query session's odometry."""
        state = self.state
        lq, lc = state.key_frame(loop.query), state.key_frame(loop.candidate)
        qs = state.sessions[query.key.session]
        partner = state.groups[qs.group].from_session[loop.candidate.session]
        return (
            partner
            @ lc.odometry_pose
            @ loop.candidate_from_query
            @ invert(lq.odometry_pose)
            @ query.odometry_pose
        )

    def placed(self, query: KeyFrame) -> np.ndarray:
        """group_from_query where the proximity search looks: chained from the query's
        session's latest loop with another session of the group (near a loop the errors of the
        placements cancel), else through its session's link (link @ odometry, whose heading
        error grows into metres along a long session)."""
        state = self.state
        qs = state.sessions[query.key.session]
        last = self._last_loop.get((qs.name, None))
        if last is not None:
            return self._chained(query, last)
        return state.groups[qs.group].from_session[qs.name] @ query.odometry_pose

    def _register(
        self, verifier, query: KeyFrame, cand: KeyFrame, distance: float, start
    ) -> tuple[LoopCandidate, LoopVerification]:
        state = self.state
        return verifier.verify_candidate(
            query.key,
            cand.key,
            query.timestamp_us,
            cand.timestamp_us,
            distance,
            state.local_map(query, past_only=True),
            state.local_map(cand, past_only=False),
            start,
            cache_keys=(state.map_key(query, True), state.map_key(cand, False)),
        )

    def check(
        self,
        query: KeyFrame,
        cand: KeyFrame,
        distance: float,
        source: str,
        verifier: str | None = None,
        hint: np.ndarray | None = None,
    ) -> tuple[LoopCandidate, LoopVerification]:
        """(record, verification) of one candidate. ``verifier`` names a field of
        :class:`Verifiers` (None: ``recognition`` or ``guided``, as the guess allows); ``hint``:
        where the search starts when neither odometry nor the map predicts the pose."""
        guess = self.guess(query, cand)
        if verifier is None:
            ver_ = self.verifiers.recognition if guess is None else self.verifiers.guided
        else:
            ver_ = getattr(self.verifiers, verifier)
        start = guess if guess is not None else hint
        record, ver = self._register(ver_, query, cand, distance, start)
        record = replace(record, source=source)
        if guess is not None and cand.key.session != query.key.session:
            # The guess came from the map (or the group): a pose far from it is a look-alike.
            limit_m = self.config.loops.map_consistency_m
            if verifier == "proximity" and self.config.loops.proximity_consistency_m is not None:
                limit_m = self.config.loops.proximity_consistency_m
            record = self.near_prediction(record, guess, "the map's prediction", limit_m)
        return record, ver

    def near_prediction(
        self, record: LoopCandidate, guess: np.ndarray, what: str, limit_m: float | None = None
    ):
        """``record`` rejected when accepted but farther than ``limit_m`` (None:
        ``loops.map_consistency_m``) or ``loops.map_consistency_deg`` from ``guess`` (``what``
        names the prediction in the reason)."""
        cfg = self.config.loops
        limit_m = cfg.map_consistency_m if limit_m is None else limit_m
        dist_m, dyaw_deg = se2_distance(guess, record.candidate_from_query)
        if record.accepted and (dist_m > limit_m or dyaw_deg > cfg.map_consistency_deg):
            reason = f"{dist_m:.1f} m / {dyaw_deg:.0f} deg from {what}"
            return replace(record, accepted=False, reason=reason)
        return record
