"""The SLAM pipeline: radar odometry + AutoPlace loop detection + registration + GTSAM pose graph.

``SlamPipeline(reader, config).run(scenes)`` reads as its list of steps. For every scene (a
*session*), frame by frame:

1. **Odometry** (:class:`~radarslam.odometry.pipeline.RadarOdometry`): Doppler ego-motion fused
   with kiss-icp scan-to-map registration; the frame's sweeps are buffered with the estimated pose.
2. At each **key frame** (~2 Hz):
   a. accumulate 5 radars x 7 sweeps with the *estimated* poses, dynamic points removed
      (:mod:`radarslam.slam.keyframes`);
   b. a pose-graph node, tied to the previous key frame by the odometry's key-frame motion and
      its covariance;
   c. **place recognition**: the AutoPlace descriptor of the last key frames (query is pure,
      insertion explicit), candidates among earlier key frames excluding the recent past of the
      same session;
   d. **verification** of each candidate by registering the two key frames' local maps
      (:class:`~radarslam.slam.loop_closure.LoopVerifier`); every candidate, accepted or not, is
      logged with the reason;
   e. **reversed search**, for a session outside the map when recognition closed nothing: every
      ``reversed_every``-th key frame queries AutoPlace with
      its images turned by 180 deg against the key frames of sessions not linked to it yet, and
      the best match is verified over headings near a half turn: how a street driven the other
      way round is found;
   f. **proximity search** when nothing else closed the key frame: once the key frame's session is
      linked to others (or revisits its own past), the nearest key frame of its group within
      ``proximity_radius_m`` of the predicted pose is registered from that prediction (ICP only).
      Recognition links sessions; proximity then closes a loop at nearly every revisiting key
      frame, which is what pulls the whole session onto the map;
   g. **merge search** (off by default), whatever closed the key frame, every
      ``merge_search_every``-th key frame while other groups exist: AutoPlace queried (plain and
      turned) among the key frames of the other groups only, the best match of each verified
      (at ``merge_min_tight_fitness``) and, accepted, a vote between the groups. Once a session
      closes loops in its own group, its recognition finds the group's own passes first and its
      proximity loops hold recognition off, so groups that overlap can stay apart; the search
      joins more of them but gives look-alike streets more chances;
   h. accepted loops become robust factors; iSAM2 receives only the new factors and values.
3. A final batch Levenberg-Marquardt, the static map, and the results folder.

Where each part lives: the odometry side (step 1) in :mod:`radarslam.slam.feed`, the helper
processes it runs in with ``pipelined`` in :mod:`radarslam.slam.processes`, the calibration pass
in :mod:`radarslam.slam.calibration_pass`; the sessions, groups and key frames in
:mod:`radarslam.slam.state`; the candidate sources (2c, 2e-2g) in :mod:`radarslam.slam.proposers`;
the verifier variants and predictions (2d) in :mod:`radarslam.slam.verification`; votes and merges
in :mod:`radarslam.slam.linking`; factors into the graph (2b, 2h) in
:mod:`radarslam.slam.insertion`; the result in :mod:`radarslam.slam.result`. This module holds
them together.

Step 1 (and the key-frame clouds) never depends on steps 2b-2h, so with ``pipelined`` (default)
it runs in a forked process that streams key-frame clouds to this one: on two cores odometry and
loop closure overlap, with identical results.

Multi-session. Each scene is its own odometry chain and starts as its own *group*, except a scene
that continues the one before it (same log, within the odometry's gap limit:
``continue_log_scenes``): its odometry drives on, it joins that scene's group in the same frame,
and the pose graph ties its first key frame to the other's last by the odometry's motion. Verified
loops between two groups are votes on their relative placement; once ``link_min_consistent_loops``
votes agree (each vote's placement puts the others' loop key frames within ``link_consistency_m``),
one of them well conditioned, the groups merge (the other votes are rejected as false loops). The
first session's group is the map: a group that merges into it enters the graph with its poses moved
there (iSAM2 never sees a chain initialised kilometres away), together with the loops found inside
it. Groups that never reach the map are added at the end on their own weak anchor and reported as
separate components, not forced into the map. When two groups merge, the key frames processed
before the link (which had no prediction then) are caught up by the proximity search against the
other side. The merged placement is the mean of the agreeing votes: each vote errs on its own,
and proximity ICP inherits the placement's error along a street, where the geometry barely
constrains it. For the same reason, inside a group outside the map (no graph corrects it there)
a prediction chains from the session's latest loop rather than from the link's placement, which
both sessions' odometry drifts away from.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from radarslam.errors import ConfigError, DataError
from radarslam.io.loops import NodeKey
from radarslam.memory import release_free_memory
from radarslam.slam.config import SlamConfig
from radarslam.slam.feed import (
    FeedMessage,
    FramesRead,
    KeyFrameInput,
    KeyFrameReady,
    OdometryFeed,
    SessionSpan,
    SessionStart,
)
from radarslam.slam.insertion import GraphInsertion
from radarslam.slam.linking import SessionLinker
from radarslam.slam.processes import can_fork
from radarslam.slam.proposers import (
    CandidateProposer,
    MergeProposer,
    Proposal,
    ProximityProposer,
    RecognitionProposer,
    TurnedProposer,
)
from radarslam.slam.result import SlamResult, SlamTimings, assemble_result
from radarslam.slam.state import KeyFrame, MapState, PendingLoop, Session, make_key_frame
from radarslam.slam.verification import Verification, Verifiers
from radarslam.types import AccumulatedCloud, SceneInfo

log = logging.getLogger("radarslam.slam")

#: Every this many key frames the heap's free pages go back to the system (radarslam.memory):
#: on the 32-scene city subset the run ends at 0.85 GB instead of 1.15 GB, at the same CPU time.
RELEASE_MEMORY_EVERY_KEY_FRAMES = 20


def _frozen(states: list[int] | None) -> frozenset[int] | None:
    return None if states is None else frozenset(states)


class SlamPipeline:
    """Single- and multi-session radar SLAM over scenes of a :class:`NuScenesRadar` reader.

    Its parts, each with its own state: :attr:`feed` (frames to key-frame clouds),
    :attr:`state` (sessions, groups, key frames, the loop log), :attr:`proposers` (where a key
    frame may have been before), :attr:`verification` (with the verifier variants in
    :attr:`verifiers`), :attr:`linker` (votes, merges) and :attr:`insertion`
    (the pose graph's factors)."""

    def __init__(self, reader, config: SlamConfig | None = None, recognizer=None, progress=True):
        from radarslam.nuscenes.filters import RadarPointFilter
        from radarslam.odometry.pipeline import KeyFrameGate, RadarOdometry
        from radarslam.slam.pose_graph import PoseGraph

        self.reader = reader
        self.config = config or SlamConfig()
        cfg = self.config
        self.progress = progress
        kc = cfg.key_frames
        self.odometry = RadarOdometry(
            cfg.odometry.model_copy(deep=True),
            KeyFrameGate(kc.min_travel_m, kc.min_turn_deg, kc.max_interval_s),
        )
        pc = cfg.odometry.points
        frame_filter = RadarPointFilter(
            _frozen(pc.invalid_states), _frozen(pc.dynprop_states), _frozen(pc.ambig_states)
        )
        self.timings = SlamTimings()
        #: Whether a calibration pass's estimate was applied to this run's odometry.
        self._calibration_applied = False
        self.feed = OdometryFeed(
            reader, cfg, self.odometry, frame_filter, self.timings, self._dpr_mask
        )
        self.graph = PoseGraph(cfg.backend.pose_graph)
        self.state = MapState(cfg, self.graph)
        self.verifiers = Verifiers.from_config(cfg)
        self.verification = Verification(cfg, self.state, self.verifiers)
        self.insertion = GraphInsertion(self.state, self.graph)
        self.linker = SessionLinker(
            cfg, self.state, self.verification, self.insertion, self._catch_up
        )
        self._proximity = ProximityProposer(cfg, self.state, self.verification.placed)
        #: Asked in this order for every key frame; the turned and proximity searches only
        #: propose when nothing closed the key frame yet, the merge search whatever did.
        self.proposers: list[CandidateProposer] = [
            RecognitionProposer(cfg, self.state, lambda: self.recognizer, self.timings),
            TurnedProposer(cfg, self.state, lambda: self.recognizer, self.timings),
            self._proximity,
            MergeProposer(cfg, self.state, lambda: self.recognizer, self.timings),
        ]
        self._recognizer = recognizer
        #: The shipped (or configured) recognizer is loaded on first use, in run() once the
        #: other processes are reading and running the odometry: torch and the weights take
        #: ~1.5 s that the odometry process would otherwise wait for.
        self._recognizer_loader = None
        if recognizer is None and cfg.loops.enabled:
            self._recognizer_loader = _RecognizerLoader(
                cfg.loops.checkpoint, cfg.loops.recognizer_config
            )
            self._check_recognizer_reference(self._recognizer_loader.config, loaded=True)
        if recognizer is not None:
            self._check_recognizer_reference(getattr(recognizer, "config", None), loaded=False)
            # its places become loop candidates, and a candidate must be a key frame of this run
            held = len(recognizer) if hasattr(recognizer, "__len__") else 0
            if held:
                raise ConfigError(
                    f"the place recognizer given to SlamPipeline holds {held} places; it must be "
                    "empty (the pipeline adds every key frame itself)"
                )
        #: run() is single-use: a second call would mix its sessions into this one's state
        self._ran = False
        self._duration_s = 0.0

    # --- what a run leaves behind ----------------------------------------------------------------

    @property
    def sessions(self) -> dict[str, Session]:
        return self.state.sessions

    @property
    def groups(self):
        return self.state.groups

    @property
    def loops(self):
        """Every loop candidate decided so far, in the order decided."""
        return self.state.loops

    @property
    def loop_information(self) -> dict[tuple[NodeKey, NodeKey], np.ndarray]:
        """Information matrix of every loop factor added, by (candidate, query)."""
        return self.insertion.loop_information

    def key_frame(self, key: NodeKey) -> KeyFrame:
        return self.state.key_frame(key)

    def key_frames(self, session: str) -> list[KeyFrame]:
        return list(self.sessions[session].key_frames)

    def session_placement(self, session: str) -> np.ndarray | None:
        """world_from_session used to insert the session's odometry chain (None: not inserted)."""
        return self.sessions[session].world_from_session

    # --- the run ---------------------------------------------------------------------------------

    def run(self, scenes: str | SceneInfo | Iterable[str | SceneInfo]) -> SlamResult:
        """SLAM over ``scenes`` (one scene or several, the first one the map), once per pipeline:
        a pipeline holds the state of its run, so a second call is an error."""
        infos = self._scene_infos(scenes)
        self._ran = True  # from here on the pipeline's state changes
        self._calibration_pass(infos)
        self._feed_key_frames(infos)
        self._check_key_frames(infos)
        self.linker.finish()
        self._insert_unlinked_groups()
        self._optimize()
        return assemble_result(
            self.state,
            self.graph,
            self.config.backend.static_map,
            self.timings,
            self._duration_s,
            self._doppler_calibration(),
            self.feed.calibrations if len(self.feed.calibrations) > 1 else None,
        )

    def _scene_infos(self, scenes) -> list[SceneInfo]:
        if self._ran:
            raise DataError("SlamPipeline.run() may be called once; create a new pipeline")
        if isinstance(scenes, (str, SceneInfo)):
            scenes = [scenes]
        try:
            scenes = list(scenes)
        except TypeError:
            raise DataError(
                f"scenes must be a scene name or a list of them, got {type(scenes).__name__}"
            ) from None
        infos = [self.reader.scene(s) for s in scenes]  # unknown names fail before any work
        if not infos:
            raise DataError("no scene to run SLAM on")
        names = [i.name for i in infos]
        if len(set(names)) != len(names):
            raise DataError(f"scene listed twice in {names}")
        return infos

    def _calibration_pass(self, infos: Sequence[SceneInfo]) -> None:
        """With ``odometry.fusion.calibration.passes: 2``, the odometry first runs over the
        scenes (each from a reset, as in the run; until ``calibration_pass_max_sigma_deg``) to
        estimate the vehicle's mounting yaws, and the run proper applies them to every sweep
        from its first frame: the anchor session's odometry no longer carries the mounting
        errors while the filter converges. An estimate that never got below the limit is not
        applied (on the three real Boston scenes, 60 s, it would move the sessions' error from
        their first pose from 0.33-0.47 m to 0.47-1.39 m). The key-frame clouds keep the
        configured calibration unless ``key_frames.cloud_calibration`` is ``applied``
        (:class:`OdometryFeed`)."""
        from radarslam.odometry.pipeline import RadarOdometry
        from radarslam.odometry.run import second_pass, single_pass
        from radarslam.slam.calibration_pass import calibration_pass

        odo = self.config.odometry
        if odo.fusion.calibration.passes < 2 or odo.fusion.calibration.yaw_bias_model != "mounting":
            return
        t0 = time.perf_counter()
        limit = self.config.calibration_pass_max_sigma_deg
        found = calibration_pass(
            self.reader,
            infos,
            single_pass(odo, dict(odo.mounting_yaw_deg)),
            self.feed.frame_filter,
            limit,
            progress=self.progress,
            forked=self.config.pipelined and can_fork(),
            continue_log_scenes=self.config.continue_log_scenes,
        )
        self.timings.calibration_pass_s += time.perf_counter() - t0
        if found.rigs > 1:
            log.warning(
                "calibration pass: the scenes come from %d radar rigs (nominal extrinsics "
                "differ) and one set of mounting yaws cannot serve them all; the run estimates "
                "each rig's calibration as it goes",
                found.rigs,
            )
            return
        if not found.converged:
            log.warning(
                "calibration pass: the mounting yaws are known to %.2f deg at best after %d of "
                "%d scenes%s (calibration_pass_max_sigma_deg: %s); the run starts from the "
                "configured calibration and estimates it as it goes",
                found.max_sigma_deg,
                found.scenes_used,
                found.scenes_total,
                ", too far from the limit for the rest to get there"
                if found.scenes_used < found.scenes_total
                else "",
                limit,
            )
            return
        self.odometry = RadarOdometry(
            second_pass(odo, found.calibration), self.odometry.key_frame_gate
        )
        self.feed.odometry = self.odometry
        self._calibration_applied = True

    def _doppler_calibration(self) -> dict | None:
        """The odometry's calibration over the run; after a calibration pass, the total (what
        the pass applied plus what the run's filter found left), as ``radarslam odometry``
        reports it."""
        from radarslam.odometry.run import total_calibration

        cal = self.feed.calibration
        if cal is None or not self._calibration_applied:
            return cal
        return total_calibration(self.odometry.config, cal)

    def _feed_key_frames(self, infos: Sequence[SceneInfo]) -> None:
        """Odometry over every frame, each key frame handled as it comes (in a forked process
        with ``pipelined``, identical results)."""
        bar = self._progress_bar(infos)
        try:
            if self.config.pipelined and can_fork():
                self.feed.run_forked(
                    infos, lambda m: self.handle(m, bar), meanwhile=self._load_recognizer
                )
            else:
                for message in self.feed.messages(infos):
                    self.handle(message, bar)
        finally:
            if bar is not None:
                bar.close()

    def _check_key_frames(self, infos: Sequence[SceneInfo]) -> None:
        """Key frames are the reference radar's key-frame sweeps: a scene without one has none."""
        names = [i.name for i in infos]
        empty = [n for n in names if n not in self.sessions or not self.sessions[n].key_frames]
        ref = self.config.key_frames.ref_channel
        if len(empty) == len(names):
            raise DataError(
                f"no key frame in scene(s) {', '.join(names)}: the reference radar {ref} "
                "(key_frames.ref_channel) has no key-frame sweep there"
            )
        for name in empty:
            log.warning(
                "%s: no key frame (the reference radar %s, key_frames.ref_channel, has no "
                "key-frame sweep there); the scene is left out of the results",
                name,
                ref,
            )

    def _insert_unlinked_groups(self) -> None:
        """Groups that never reached the map: each on its own weak anchor, a separate
        component of the graph."""
        for group in list(self.groups.values()):
            if not group.in_map:
                self.insertion.insert_group(group, anchor="unknown")

    def _optimize(self) -> None:
        t0 = time.perf_counter()
        self.graph.update()
        self.graph.optimize_batch()
        self.timings.final_optimization_s += time.perf_counter() - t0

    # --- the key-frame side ----------------------------------------------------------------------

    def handle(self, message: FeedMessage, bar=None) -> None:
        """One message of the feed."""
        if isinstance(message, SessionStart):
            self.start_session(message.name, message.continues)
        elif isinstance(message, KeyFrameReady):
            self.add_key_frame(message.session, message.frame, message.cloud)
        elif isinstance(message, FramesRead):
            if bar is not None:
                bar.update(message.count)
        elif isinstance(message, SessionSpan):
            self._duration_s += (message.last_us - message.first_us) * 1e-6
        else:  # a programming error, not a data problem
            raise AssertionError(f"unknown message {message!r}")

    def start_session(self, name: str, continues: str | None = None) -> Session:
        return self.state.start_session(
            name, log=self.reader.scene(name).log_token, continues=continues
        )

    def add_key_frame(self, session_name: str, inp: KeyFrameInput, cloud) -> KeyFrame:
        """A key frame of the session: a graph node, then loop closing, then iSAM2."""
        session = self.sessions[session_name]
        kf = make_key_frame(session, inp, cloud, self.state.previous_key_frame(session))
        self.state.add(kf)
        self.timings.key_frames += 1

        if session.inserted:
            self.insertion.add_node(session, kf)
        elif kf.key.index == 0 and session.index == 0:
            self.groups[session.group].in_map = True
            self.insertion.insert_group(self.groups[session.group], anchor="prior")
        elif kf.key.index == 0 and self.groups[session.group].in_map:
            # a continued session of the map: its chain goes on from the one it continues
            group = self.groups[session.group]
            self.insertion.insert_session(session, group.from_session[session.name], "unknown")

        if self.recognizer is not None:
            self._close_loops(session, kf, cloud)
        t2 = time.perf_counter()
        if session.inserted:
            self.timings.isam2_update_ms.append(1e3 * self.graph.update())
        self.timings.backend_s += time.perf_counter() - t2
        if self.timings.key_frames % RELEASE_MEMORY_EVERY_KEY_FRAMES == 0:
            release_free_memory()
        return kf

    def _close_loops(self, session: Session, kf: KeyFrame, cloud: AccumulatedCloud) -> None:
        """Every proposer in turn, each candidate verified as it comes."""
        t0 = time.perf_counter()
        booked = self.timings.place_recognition_s  # the proposers book their descriptor time
        closed = False
        verified: set[tuple[NodeKey, str]] = set()  # a candidate two proposers found: once
        for proposer in self.proposers:
            accepted = False
            for proposal in proposer.propose(session, kf, cloud, closed):
                if (proposal.candidate.key, proposal.search) in verified:
                    continue
                verified.add((proposal.candidate.key, proposal.search))
                accepted |= self.verify(session, kf, proposal)
            proposer.settle(session, kf, accepted)
            closed |= accepted
        booked = self.timings.place_recognition_s - booked
        self.timings.verification_s += time.perf_counter() - t0 - booked

    def verify(self, session: Session, query: KeyFrame, proposal: Proposal) -> bool:
        """Verify one candidate; True when it was accepted (into the graph, a group or a vote)."""
        cand = proposal.candidate
        record, ver = self.verification.check(
            query, cand, proposal.distance, proposal.source, proposal.verifier, proposal.hint
        )
        cand_session = self.sessions[cand.key.session]
        if not record.accepted:
            self.loops.append(record)
            return False
        loop = PendingLoop(record, ver.information)
        self.linker.closed.add(query.key)  # before a merge: its catch-up need not search it
        if session.group == cand_session.group:
            if session.inserted:
                self.insertion.add_loop(record, ver.information)
            else:
                self.groups[session.group].loops.append(loop)
            if cand_session is not session:
                self.verification.note_loop(record)
        else:  # between two groups: a vote on where one lies in the other
            self.linker.vote(session, loop)
        session.last_loop_kf = query.key.index
        return True

    def _catch_up(self, side_a: list[str], side_b: list[str]) -> None:
        """Proximity search for the key frames processed before their sessions were linked: each
        key frame not yet closed looks for its revisit among the other side's earlier sessions
        (the query of a loop is always the later key frame)."""
        if self.config.loops.proximity_radius_m is None:
            return
        for mine, theirs in ((side_a, side_b), (side_b, side_a)):
            for name in mine:
                session = self.sessions[name]
                earlier = {n for n in theirs if self.sessions[n].index < session.index}
                if not earlier:
                    continue
                for kf in list(session.key_frames):
                    if kf.key in self.linker.closed:
                        continue
                    for proposal in self._proximity.candidates(session, kf, among=earlier):
                        self.verify(session, kf, proposal)

    # --- the place recognizer --------------------------------------------------------------------

    def _load_recognizer(self) -> None:
        if self._recognizer_loader is not None:
            self._recognizer = self._recognizer_loader.load()
            self._recognizer_loader = None

    @property
    def recognizer(self):
        """The place recognizer (None: loop detection off)."""
        self._load_recognizer()
        return self._recognizer

    def _check_recognizer_reference(self, recognizer_config, loaded: bool) -> None:
        """The key frames are accumulated in the frame of ``key_frames.ref_channel``; the
        recognizer's images must be centred on the same radar (else every key frame fails)."""
        acc = getattr(recognizer_config, "accumulation", None)
        want = getattr(acc, "ref_channel", None)
        have = self.config.key_frames.ref_channel
        if want is not None and want != have:
            source = (
                f"recognizer config {self.config.loops.recognizer_config}"
                if loaded and self.config.loops.recognizer_config is not None
                else "the place recognizer"
            )
            raise ConfigError(
                f"key_frames.ref_channel={have} but {source} centres its images on {want} "
                "(accumulation.ref_channel); both must name the same radar"
            )

    def _dpr_mask(self):
        if self.recognizer is None:
            from radarslam.place_recognition.config import DPRConfig
            from radarslam.place_recognition.dpr import make_point_mask

            return make_point_mask(DPRConfig())
        from radarslam.place_recognition.dpr import make_point_mask

        return make_point_mask(self.recognizer.config.dpr)

    def _progress_bar(self, infos: Sequence[SceneInfo]):
        if not self.progress:
            return None
        from tqdm import tqdm

        total = sum(self.reader.frame_count(i) for i in infos)  # as the feed iterates them
        return tqdm(total=total, unit="frame", desc="slam", leave=False)


class _RecognizerLoader:
    """:func:`load_recognizer` in two steps: the recognizer config and the checkpoint's presence
    are checked when made (a bad one fails before any work), torch and the weights are loaded by
    :meth:`load`."""

    def __init__(self, checkpoint: str | None, recognizer_config: str | None):
        from radarslam.config import CONFIG_DIR, load_config
        from radarslam.place_recognition.config import PlaceRecognizerConfig
        from radarslam.place_recognition.recognizer import checkpoint_path

        self.checkpoint = checkpoint
        self.config = PlaceRecognizerConfig()  # what PlaceRecognizer uses when given none
        if recognizer_config is not None:
            path = Path(recognizer_config)
            if not path.is_absolute() and not path.exists():
                path = CONFIG_DIR / path
            self.config = load_config(PlaceRecognizerConfig, path)
        checkpoint_path(checkpoint)

    def load(self):
        from radarslam.place_recognition.recognizer import PlaceRecognizer

        return PlaceRecognizer(checkpoint=self.checkpoint, config=self.config)


def load_recognizer(checkpoint: str | None, recognizer_config: str | None):
    """The place recognizer for the pipeline (shipped compact checkpoint by default)."""
    return _RecognizerLoader(checkpoint, recognizer_config).load()


__all__ = ["KeyFrame", "SlamPipeline", "SlamResult", "SlamTimings", "load_recognizer"]
