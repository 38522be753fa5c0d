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
      ``reversed_every``-th key frame (less often after repeated misses) queries AutoPlace with
      its images turned by 180 deg against other sessions' key frames (``reversed_targets``:
      those not linked to it yet, or only the map's), and the best match is verified
      over headings near a half turn: how a street driven the other way round is found;
   f. **proximity search** when nothing else closed the key frame: once the key frame's session is
      linked to others (or revisits its own past), the nearest key frame of its group within
      ``proximity_radius_m`` of the predicted pose is registered from that prediction (ICP only).
      Recognition links sessions; proximity then closes a loop at nearly every revisiting key
      frame, which is what pulls the whole session onto the map;
   g. accepted loops become robust factors; iSAM2 receives only the new factors and values.
3. A final batch Levenberg-Marquardt, the static map, and the results folder.

Step 1 (and the key-frame clouds) never depends on steps 2b-2g, so with ``pipelined`` (default)
it runs in a forked process that streams key-frame clouds to this one: on two cores odometry and
loop closure overlap, with identical results.

Multi-session. Each scene is its own odometry chain and starts as its own *group*. Verified loops
between two groups are votes on their relative placement; once ``link_min_consistent_loops`` votes
agree (each vote's placement puts the others' loop key frames within ``link_consistency_m``), the
groups merge (the other votes are rejected as false loops). A global registration that failed the
tight-fitness or RMSE test by a little, if well conditioned, is a weak vote: it counts only towards
a link of ``weak_link_min_votes`` agreeing votes, one of them a full loop. A lone vote is checked
where it predicts the session lies: earlier (then later) key frames of its session, spaced apart,
are registered from that prediction, and enough of them accepted near it link the groups
(``loops.confirm_*``; a street driven the other way rarely gives two global matches). The first
session's group is the map: a group that merges into it enters the graph with its poses moved
there (iSAM2 never sees a chain initialised kilometres away), together with the loops found inside
it. Groups that never reach the map are added at the end on their own weak anchor and reported as
separate components, not forced into the map. When two groups merge, the key frames processed
before the link (which had no prediction then) are caught up by the proximity search against the
other side. The merged placement is the mean of the agreeing votes: each vote errs on its own,
and proximity ICP inherits the placement's error along a street, where the geometry barely
constrains it. For the same reason, inside a group outside the map (no graph corrects it there)
a prediction chains from the session's latest loop rather than from the link's placement, which
both sessions' odometry drifts away from (``loops.guess_from_last_loop``).
"""

from __future__ import annotations

import bisect
import logging
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from radarslam.errors import ConfigError, DataError
from radarslam.geometry import invert, se2_to_matrix, wrap_angle, yaw_of
from radarslam.io.loops import LoopCandidate, NodeKey
from radarslam.slam.config import SlamConfig
from radarslam.slam.feed import (
    FeedMessage,
    FramesRead,
    KeyFrameInput,
    KeyFrameReady,
    OdometryFeed,
    SessionSpan,
    SessionStart,
    can_fork,
)
from radarslam.types import AccumulatedCloud, SceneInfo

log = logging.getLogger("radarslam.slam")

#: Odometry covariance (x, y, yaw) used where the odometry chain broke (a long gap in the data).
_BROKEN_CHAIN_SIGMAS = np.array([10.0, 10.0, 0.5])


#: A half turn about the z axis.
_HALF_TURN = np.diag([-1.0, -1.0, 1.0, 1.0])


def turned_cloud(cloud: AccumulatedCloud) -> AccumulatedCloud:
    """The cloud turned by 180 deg about its reference sensor: roughly what the sensor sees of
    the same place when the street is driven the other way round (the far field, which only the
    forward radar reaches, stays on the wrong side). Its sample token gets a ``#turned`` suffix
    so that a recognizer's per-token feature cache keeps the two apart."""
    points = cloud.points.copy()
    for name in ("x", "y", "vx", "vy", "vx_comp", "vy_comp"):
        if name in points.dtype.names:
            points[name] = -points[name]
    return replace(
        cloud,
        points=points,
        world_from_ref=cloud.world_from_ref @ _HALF_TURN,
        sample_token=f"{cloud.sample_token}#turned" if cloud.sample_token else "",
    )


@dataclass
class KeyFrame:
    key: NodeKey
    timestamp_us: int
    sample_token: str
    odometry_pose: np.ndarray  # world_from_ego in the session's odometry frame
    gt_pose: np.ndarray  # ground truth, kept for the outputs only (never used by the estimate)
    cloud_xy_ego: np.ndarray  # (N, 2) static points of the key-frame cloud, ego frame
    cloud_points: np.ndarray  # the accumulated cloud (reference-radar frame), for the map
    ego_from_ref: np.ndarray
    relative: np.ndarray | None = None  # prev_ego_from_ego from the odometry
    relative_cov: np.ndarray | None = None


@dataclass
class _PendingLoop:
    """A verified loop not yet in the graph."""

    record: LoopCandidate
    information: np.ndarray
    #: failed verification by a little (``loops.weak_vote_*``): counts only towards a weak link
    weak: bool = False


@dataclass
class _Confirmation:
    """A lone vote between two groups whose predicted placement is being checked at other key
    frames of its query's session (``loops.confirm_*``)."""

    vote: _PendingLoop
    taken: list[np.ndarray]  # group-frame positions of the key frames used (the vote's first)
    confirmed: list[_PendingLoop] = field(default_factory=list)
    checks: int = 0


@dataclass
class _Group:
    """Sessions placed relative to each other by consistent loops; ``in_map`` for the group of
    the anchored session, the one processed first (its frame is the world)."""

    index: int
    from_session: dict[str, np.ndarray] = field(default_factory=dict)  # group_from_session
    in_map: bool = False
    loops: list[_PendingLoop] = field(default_factory=list)  # inside the group, not in the graph


@dataclass
class _Session:
    name: str
    index: int
    group: int = -1
    key_frames: list[KeyFrame] = field(default_factory=list)
    inserted: bool = False
    world_from_session: np.ndarray | None = None  # where the chain was put in the map
    last_loop_kf: int = -(10**9)
    last_reversed_kf: int = -(10**9)  # the last key frame that ran the reversed search
    reversed_misses: int = 0  # reversed searches since the last accepted one
    timestamps_us: list[int] = field(default_factory=list)  # of the key frames, increasing
    _xy: np.ndarray = field(default_factory=lambda: np.zeros((64, 2)))  # grows by doubling

    def add_position(self, xy: np.ndarray) -> None:
        n = len(self.timestamps_us) - 1  # the key frame's index (its timestamp is in already)
        if n >= len(self._xy):
            self._xy = np.concatenate([self._xy, np.zeros_like(self._xy)])
        self._xy[n] = xy

    def positions(self) -> np.ndarray:
        """(N, 2) odometry positions of the key frames so far (a view, no copy)."""
        return self._xy[: len(self.timestamps_us)]


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
        )


@dataclass
class SlamResult:
    sessions: list  # list[radarslam.slam.outputs.SessionResult]
    loops: list[LoopCandidate]
    components: list  # list[radarslam.slam.pose_graph.GraphComponent]
    static_map: object | None
    timings: SlamTimings
    duration_s: float  # sensor time covered by the run
    graph: object = None  # the PoseGraph, for marginals / g2o export

    @property
    def accepted_loops(self) -> list[LoopCandidate]:
        return [c for c in self.loops if c.accepted]


def _se2_distance(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    d = invert(a) @ b
    return float(np.hypot(d[0, 3], d[1, 3])), float(
        abs(np.degrees(wrap_angle(np.arctan2(d[1, 0], d[0, 0]))))
    )


def _se2_mean(poses: list[np.ndarray]) -> np.ndarray:
    """Mean of nearby planar poses: mean translation, circular mean of the yaw."""
    t = np.mean([p[:2, 3] for p in poses], axis=0)
    yaws = np.array([np.arctan2(p[1, 0], p[0, 0]) for p in poses])
    yaw = float(np.arctan2(np.sin(yaws).mean(), np.cos(yaws).mean()))
    return se2_to_matrix(float(t[0]), float(t[1]), yaw)


class SlamPipeline:
    """Single- and multi-session radar SLAM over scenes of a :class:`NuScenesRadar` reader."""

    def __init__(self, reader, config: SlamConfig | None = None, recognizer=None, progress=True):
        from radarslam.nuscenes.filters import RadarPointFilter
        from radarslam.odometry.pipeline import KeyFrameGate, RadarOdometry
        from radarslam.slam.loop_closure import LoopVerifier
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
        self._frame_filter = RadarPointFilter(pc.invalid_states, pc.dynprop_states, pc.ambig_states)
        self.timings = SlamTimings()
        self.feed = OdometryFeed(
            reader, cfg, self.odometry, self._frame_filter, self.timings, self._dpr_mask
        )
        self.graph = PoseGraph(cfg.backend.pose_graph)
        self.verifier = LoopVerifier(cfg.backend.loop_verification)
        self.guided_verifier = LoopVerifier(
            cfg.backend.loop_verification.model_copy(
                update={
                    "heading_step_deg": 360.0,  # one hypothesis: the predicted heading
                    "search_radius_m": cfg.loops.guided_search_radius_m,
                    "refine_top_k": 1,
                }
            )
        )
        # Proximity candidates come with the map's prediction, good to a metre or two: ICP from
        # it alone, no search over headings and translations.
        proximity = cfg.backend.loop_verification.model_copy(
            update={
                "heading_step_deg": 360.0,
                "correlative_search": False,
                "refine_top_k": 1,
                "max_range_m": cfg.loops.proximity_max_range_m,
                "min_tight_fitness": cfg.loops.proximity_min_tight_fitness,
                "icp_relative_tolerance": cfg.loops.proximity_icp_relative_tolerance,
            }
        )
        # Lone votes are confirmed from their prediction the same way, but on every point: the
        # constraint-ratio test they rely on was calibrated on maps with the clutter in.
        self.confirmation_verifier = LoopVerifier(proximity)
        if cfg.loops.proximity_min_neighbors is not None:
            proximity = proximity.model_copy(
                update={"min_neighbors": cfg.loops.proximity_min_neighbors}
            )
        self.proximity_verifier = LoopVerifier(proximity)
        # Turned-image candidates come with a rough relative heading (half a turn) but no
        # position: the global translation search, over headings near 180 deg only.
        self.reversed_verifier = LoopVerifier(
            cfg.backend.loop_verification.model_copy(
                update={
                    "heading_range_deg": cfg.loops.reversed_heading_range_deg,
                    "refine_top_k": 1,
                }
            )
        )
        self.scancontext = None
        if cfg.loops.enabled and cfg.loops.scancontext_search:
            from radarslam.slam.scancontext_candidates import ScanContextCandidates

            self.scancontext = ScanContextCandidates(cfg.loops.scancontext_ring_candidates)
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
        self.sessions: dict[str, _Session] = {}
        self.groups: dict[int, _Group] = {}
        #: Verified loops between two groups, waiting for a consistent partner to merge them.
        self._votes: list[_PendingLoop] = []
        self._confirming: list[_Confirmation] = []
        # (query session, candidate session or None: any) -> the latest loop inside one group
        self._last_loop: dict[tuple[str, str | None], LoopCandidate] = {}
        self.loops: list[LoopCandidate] = []
        self._kf_by_key: dict[NodeKey, KeyFrame] = {}
        self._duration_s = 0.0
        #: Information matrix of every loop factor added, by (candidate, query).
        self.loop_information: dict[tuple[NodeKey, NodeKey], np.ndarray] = {}
        #: Key frames that are the query of an accepted loop (a vote, in a group or in the map).
        self._closed: set[NodeKey] = set()

    # --- the run ---------------------------------------------------------------------------------

    def run(self, scenes: str | SceneInfo | Iterable[str | SceneInfo]) -> SlamResult:
        """SLAM over ``scenes`` (one scene or several, the first one the map), once per pipeline:
        a pipeline holds the state of its run, so a second call is an error."""
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
        self._ran = True  # from here on the pipeline's state changes
        bar = self._progress_bar(infos)
        try:
            if self.config.pipelined and can_fork():
                self.feed.run_forked(
                    infos, lambda m: self._handle(m, bar), meanwhile=self._load_recognizer
                )
            else:
                for message in self.feed.messages(infos):
                    self._handle(message, bar)
        finally:
            if bar is not None:
                bar.close()
        # Key frames are the reference radar's key-frame sweeps: a scene without one has none.
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
        for hyp in list(self._confirming):  # the last session ended before enough checks
            self._settle(hyp)
        for vote in self._votes:  # never confirmed by a consistent second loop
            if vote.weak:  # rejected by verification all along
                self.loops.append(vote.record)
                continue
            self.loops.append(
                replace(
                    vote.record,
                    accepted=False,
                    reason="too few consistent loops to link the session",
                )
            )
        self._votes = []
        for group in list(self.groups.values()):
            if not group.in_map:
                self._insert_group(group, anchor="unknown")  # a separate component
        t0 = time.perf_counter()
        self.graph.update()
        self.graph.optimize_batch()
        self.timings.final_optimization_s += time.perf_counter() - t0
        return self._result()

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

    # --- the odometry side: frames -> key-frame clouds -------------------------------------------

    def _handle(self, message: FeedMessage, bar) -> None:
        if isinstance(message, SessionStart):
            self._start_session(message.name)
        elif isinstance(message, KeyFrameReady):
            self._key_frame(message.session, message.frame, message.cloud)
        elif isinstance(message, FramesRead):
            if bar is not None:
                bar.update(message.count)
        elif isinstance(message, SessionSpan):
            self._duration_s += (message.last_us - message.first_us) * 1e-6
        else:  # a programming error, not a data problem
            raise AssertionError(f"unknown message {message!r}")

    # --- the key-frame side -----------------------------------------------------------------------

    def _start_session(self, name: str) -> None:
        for hyp in list(self._confirming):  # the earlier sessions get no more key frames
            self._settle(hyp)
        session = _Session(name, len(self.sessions))
        self.sessions[name] = session
        group = _Group(session.index, {name: np.eye(4)})  # unique: merges delete groups
        self.groups[group.index] = group
        session.group = group.index

    def _key_frame(self, session_name: str, inp: KeyFrameInput, cloud) -> None:
        session = self.sessions[session_name]
        ego_from_ref = inp.ego_from_ref
        xy_ref = np.column_stack([cloud.points["x"], cloud.points["y"]])
        xy_ego = xy_ref @ ego_from_ref[:2, :2].T + ego_from_ref[:2, 3]
        index = len(session.key_frames)
        prev = session.key_frames[-1] if session.key_frames else None
        kf = KeyFrame(
            key=NodeKey(session.name, index),
            timestamp_us=inp.timestamp_us,
            sample_token=inp.sample_token,
            odometry_pose=inp.odometry_pose,
            gt_pose=inp.gt_pose,
            cloud_xy_ego=xy_ego,
            cloud_points=cloud.points,
            ego_from_ref=ego_from_ref,
        )
        if prev is not None:
            if inp.motion is not None:
                kf.relative = inp.motion
                kf.relative_cov = inp.motion_cov
            else:  # the odometry restarted (gap in the data): a weak link keeps the chain whole
                kf.relative = invert(prev.odometry_pose) @ kf.odometry_pose
                kf.relative_cov = np.diag(np.square(_BROKEN_CHAIN_SIGMAS))
        session.key_frames.append(kf)
        session.timestamps_us.append(kf.timestamp_us)
        session.add_position(kf.odometry_pose[:2, 3])
        self._kf_by_key[kf.key] = kf
        self.timings.key_frames += 1

        if session.inserted:
            self._add_node(session, kf)
        elif index == 0 and session.index == 0:
            self.groups[session.group].in_map = True
            self._insert_group(self.groups[session.group], anchor="prior")

        if self.recognizer is not None:
            self._detect_loops(session, kf, cloud)
            if self._confirming:
                self._confirm_with(kf)
        t2 = time.perf_counter()
        if session.inserted:
            self.timings.isam2_update_ms.append(1e3 * self.graph.update())
        self.timings.backend_s += time.perf_counter() - t2

    def _add_node(self, session: _Session, kf: KeyFrame) -> None:
        if kf.key.index == 0:
            return
        self.graph.add_odometry(
            session.name, kf.key.index - 1, kf.key.index, kf.relative, kf.relative_cov
        )

    # --- loops ----------------------------------------------------------------------------------

    def _detect_loops(self, session: _Session, kf: KeyFrame, cloud) -> None:
        cfg = self.config.loops
        t0 = time.perf_counter()
        desc, rcs = self._describe(session, kf, cloud)
        candidates = []
        if kf.key.index - session.last_loop_kf > cfg.min_key_frames_between_loops:
            candidates = self.recognizer.query_descriptor(
                desc, rcs, k=cfg.num_candidates, exclude=self._excluded(kf)
            )
        self.recognizer.add_descriptor(desc, rcs, kf.key)
        t1 = time.perf_counter()
        self.timings.place_recognition_s += t1 - t0
        budget = None if session.inserted else cfg.unlinked_candidates_per_key_frame
        closed = False
        for cand in candidates:
            gate = cfg.max_descriptor_distance
            if gate is not None and cand.descriptor_distance > gate:
                continue
            if budget is not None:
                if budget == 0:
                    break
                budget -= 1
            closed |= self._verify(session, kf, self._kf_by_key[cand.key], cand.descriptor_distance)
        recognition_s = self.timings.place_recognition_s
        if not closed and cfg.reversed_search:
            closed |= self._reversed_search(session, kf, cloud)
        if self.scancontext is not None:  # every key frame goes into its database
            closed |= self._scancontext_search(session, kf, search=not closed)
        if not closed:
            for other in self._proximity_candidates(session, kf):
                self._verify(session, kf, other, float("nan"), self.proximity_verifier)
        # the reversed and ScanContext searches book their descriptor time themselves
        recognition_s = self.timings.place_recognition_s - recognition_s
        self.timings.verification_s += time.perf_counter() - t1 - recognition_s

    def _reversed_search(self, session: _Session, kf: KeyFrame, cloud) -> bool:
        """For a session outside the map: AutoPlace queried with the key frame's image sequence
        turned by 180 deg, i.e. as the street looks driven the other way round, against the
        key frames of ``loops.reversed_targets``; the best match is verified by the translation
        search over headings near 180 deg (see ``loops.reversed_search``)."""
        cfg = self.config.loops
        interval = cfg.reversed_every
        if cfg.reversed_backoff_searches is not None:
            interval <<= min(session.reversed_misses // cfg.reversed_backoff_searches, 2)
        if (
            self.groups[session.group].in_map
            or kf.key.index < self.config.key_frames.local_map_neighbors
            or kf.key.index - session.last_reversed_kf < interval
            or kf.key.index - session.last_loop_kf <= cfg.min_key_frames_between_loops
        ):
            return False
        session.last_reversed_kf = kf.key.index
        t0 = time.perf_counter()
        sequence = self._sequence(session, cloud)
        desc, rcs = self.recognizer.describe([turned_cloud(c) for c in sequence])
        if cfg.reversed_targets == "map":

            def exclude(key: NodeKey) -> bool:
                return not self.sessions[key.session].inserted
        else:
            group = session.group

            def exclude(key: NodeKey) -> bool:
                return self.sessions[key.session].group == group

        candidates = self.recognizer.query_descriptor(desc, rcs, k=1, exclude=exclude)
        self.timings.place_recognition_s += time.perf_counter() - t0
        closed = False
        for cand in candidates:
            closed |= self._verify(
                session,
                kf,
                self._kf_by_key[cand.key],
                cand.descriptor_distance,
                self.reversed_verifier,
                source="reversed",
                hint=_HALF_TURN,
            )
        session.reversed_misses = 0 if closed else session.reversed_misses + 1
        return closed

    def _scancontext_search(self, session: _Session, kf: KeyFrame, search: bool) -> bool:
        """For a session outside the map: the best rotation-invariant candidate among the other
        groups' key frames, verified by the global search (see ``loops.scancontext_search``).
        The key frame is then stored for later queries either way."""
        cfg = self.config
        t0 = time.perf_counter()
        context = self.scancontext.describe(kf.cloud_xy_ego)
        candidates = []
        if (
            search
            and not self.groups[session.group].in_map
            and kf.key.index >= cfg.key_frames.local_map_neighbors
            and kf.key.index % cfg.loops.scancontext_every == 0
            and kf.key.index - session.last_loop_kf > cfg.loops.min_key_frames_between_loops
        ):
            group = session.group
            candidates = self.scancontext.query(
                kf.cloud_xy_ego,
                lambda key: self.sessions[key.session].group != group,
                k=1,
                context=context,
            )
        self.scancontext.add(kf.key, kf.cloud_xy_ego, context)
        self.timings.place_recognition_s += time.perf_counter() - t0
        closed = False
        for cand in candidates:
            closed |= self._verify(
                session, kf, self._kf_by_key[cand.key], cand.distance, source="scancontext"
            )
        return closed

    def _proximity_candidates(
        self, session: _Session, kf: KeyFrame, among: set[str] | None = None
    ) -> list[KeyFrame]:
        """Key frames of the query's group (of its sessions ``among``, if given) near the query's
        predicted position, nearest first, at most one per session (the query's own recent past
        excluded)."""
        cfg = self.config.loops
        if cfg.proximity_radius_m is None:
            return []
        group = self.groups[session.group]
        # Candidates and query are placed the same way (group link @ odometry) so that a common
        # error of the link cancels; the verification's guess then uses the graph's estimate.
        query_xy = (group.from_session[session.name] @ kf.odometry_pose)[:2, 3]
        found = self._near_key_frames(group, query_xy, among, recent_of=kf)
        return [k for _, k in found[: cfg.proximity_candidates]]

    def _near_key_frames(
        self,
        group: _Group,
        xy: np.ndarray,
        among: set[str] | None = None,
        recent_of: KeyFrame | None = None,
    ) -> list[tuple[float, KeyFrame]]:
        """(distance, key frame) of the group's key frames within ``proximity_radius_m`` of
        ``xy`` (group frame, key frames placed by link @ odometry), nearest first, at most one
        per session (of the sessions ``among``, if given; ``recent_of``'s recent past left out)."""
        cfg = self.config.loops
        found: list[tuple[float, KeyFrame]] = []
        for name, group_from_session in group.from_session.items():
            if among is not None and name not in among:
                continue
            other = self.sessions[name]
            pos = other.positions()
            if recent_of is not None and name == recent_of.key.session:
                recent_us = recent_of.timestamp_us - cfg.exclude_recent_s * 1e6
                pos = pos[: bisect.bisect_left(other.timestamps_us, recent_us)]
            if not len(pos):
                continue
            pos = pos @ group_from_session[:2, :2].T + group_from_session[:2, 3]
            d = np.hypot(*(pos - xy).T)
            i = int(np.argmin(d))
            if d[i] <= cfg.proximity_radius_m:
                found.append((float(d[i]), other.key_frames[i]))
        found.sort(key=lambda t: t[0])
        return found

    def _describe(self, session: _Session, kf: KeyFrame, cloud) -> tuple[np.ndarray, np.ndarray]:
        """The key frame's AutoPlace descriptor over (t-2, t-1, t); the recognizer encodes each
        key frame's image once (its feature cache is keyed by sample token)."""
        return self.recognizer.describe(self._sequence(session, cloud))

    def _sequence(self, session: _Session, cloud) -> list[AccumulatedCloud]:
        """The clouds of AutoPlace's sequence ending at the session's newest key frame, whose
        cloud is ``cloud``: its ``seq_len - 1`` predecessors, oldest first, then ``cloud``."""
        n = self.recognizer.seq_len
        return [*(self._cloud_of(k) for k in session.key_frames[-n:-1]), cloud]

    def _cloud_of(self, kf: KeyFrame):
        return AccumulatedCloud(
            points=kf.cloud_points,
            world_from_ref=kf.odometry_pose @ kf.ego_from_ref,
            ref_channel=self.config.key_frames.ref_channel,
            timestamp_us=kf.timestamp_us,
            sample_token=kf.sample_token,
        )

    def _excluded(self, kf: KeyFrame) -> Callable[[NodeKey], bool]:
        """Keys a query may not return: the recent past of its own pass."""
        recent_us = self.config.loops.exclude_recent_s * 1e6

        def skip(key: NodeKey) -> bool:
            if key.session != kf.key.session:
                return False
            return kf.timestamp_us - self._kf_by_key[key].timestamp_us < recent_us

        return skip

    def _cand_past(self, guess: np.ndarray | None) -> bool:
        """Whether the candidate's local map takes its past key frames only
        (``key_frames.candidate_map``), given the predicted candidate_from_query or None."""
        mode = self.config.key_frames.candidate_map
        if mode == "past_if_reversed":
            return guess is not None and abs(yaw_of(guess)) > np.pi / 2
        return mode == "past"

    def _window(self, kf: KeyFrame, past_only: bool) -> tuple[int, int]:
        """[lo, hi) of the key frames in ``kf``'s local map (its session's, so far)."""
        n = self.config.key_frames.local_map_neighbors
        frames = self.sessions[kf.key.session].key_frames
        lo = max(0, kf.key.index - n)
        hi = kf.key.index + 1 if past_only else min(len(frames), kf.key.index + n + 1)
        return lo, hi

    def _map_key(self, kf: KeyFrame, past_only: bool) -> tuple:
        """Names a local map's content for the verifiers' caches: odometry poses and clouds
        never change, so the key frame and its window determine the points."""
        return (kf.key, *self._window(kf, past_only))

    def _local_map(self, kf: KeyFrame, past_only: bool) -> np.ndarray:
        frames = self.sessions[kf.key.session].key_frames
        lo, hi = self._window(kf, past_only)
        ego_from_world = invert(kf.odometry_pose)
        chunks = []
        for other in frames[lo:hi]:
            t = ego_from_world @ other.odometry_pose
            chunks.append(other.cloud_xy_ego @ t[:2, :2].T + t[:2, 3])
        return np.concatenate(chunks) if chunks else np.zeros((0, 2))

    def _pose_in_group(self, kf: KeyFrame) -> np.ndarray:
        """The key frame's pose in its group's frame (the graph's estimate once in the map)."""
        session = self.sessions[kf.key.session]
        if session.inserted:
            return self.graph.current_pose(kf.key)
        return self.groups[session.group].from_session[session.name] @ kf.odometry_pose

    def _guess(self, query: KeyFrame, cand: KeyFrame) -> np.ndarray | None:
        qs, cs = self.sessions[query.key.session], self.sessions[cand.key.session]
        if qs is cs:
            return invert(cand.odometry_pose) @ query.odometry_pose
        if qs.group != cs.group:
            return None
        last = self._last_loop.get((qs.name, cs.name)) or self._last_loop.get((qs.name, None))
        if not qs.inserted and last is not None and self.config.loops.guess_from_last_loop:
            # Outside the map no graph corrects the placements, and both odometry chains drift
            # from where the sessions were linked: chain from the query session's latest loop
            # (with the candidate's session if there is one) over a short span of odometry.
            lq, lc = self._kf_by_key[last.query], self._kf_by_key[last.candidate]
            partner = self.groups[qs.group].from_session[last.candidate.session]
            query_in_group = (
                partner
                @ lc.odometry_pose
                @ last.candidate_from_query
                @ invert(lq.odometry_pose)
                @ query.odometry_pose
            )
            return invert(self._pose_in_group(cand)) @ query_in_group
        return invert(self._pose_in_group(cand)) @ self._pose_in_group(query)

    def _verify(
        self,
        session: _Session,
        query: KeyFrame,
        cand: KeyFrame,
        distance: float,
        verifier=None,
        source: str | None = None,
        hint: np.ndarray | None = None,
    ) -> bool:
        """Verify one candidate; True when it was accepted (into the graph, a group or a vote).
        ``hint``: where the search starts when neither odometry nor the map predicts the pose."""
        guess = self._guess(query, cand)
        if source is None:
            source = "recognition" if verifier is None else "proximity"
        if verifier is None:
            verifier = self.verifier if guess is None else self.guided_verifier
        cand_past = self._cand_past(guess)
        record, ver = verifier.verify_candidate(
            query.key,
            cand.key,
            query.timestamp_us,
            cand.timestamp_us,
            distance,
            self._local_map(query, past_only=True),
            self._local_map(cand, past_only=cand_past),
            guess if guess is not None else hint,
            cache_keys=(self._map_key(query, True), self._map_key(cand, cand_past)),
        )
        record = replace(record, source=source)
        cand_session = self.sessions[cand.key.session]
        if guess is not None and cand_session is not session:
            # The guess came from the map (or the group): a pose far from it is a look-alike.
            record = self._near_prediction(record, guess, "the map's prediction")
        if not record.accepted:
            if guess is None and cand_session.group != session.group and self._weak(record):
                self._votes.append(_PendingLoop(record, ver.information, weak=True))
                self._try_merge(session.group, cand_session.group)
                return False
            self.loops.append(record)
            return False
        loop = _PendingLoop(record, ver.information)
        self._closed.add(query.key)  # before a merge: its catch-up need not search this one
        if session.group == cand_session.group:
            if session.inserted:
                self._add_loop(record, ver.information)
            else:
                self.groups[session.group].loops.append(loop)
            if cand_session is not session:
                self._last_loop[(session.name, cand_session.name)] = record
                self._last_loop[(session.name, None)] = record
        else:  # between two groups: a vote on where one lies in the other
            self._votes.append(loop)
            self._try_merge(session.group, cand_session.group)
            if session.group != cand_session.group:
                self._confirm_vote(session, loop)
        session.last_loop_kf = query.key.index
        return True

    def _near_prediction(self, record: LoopCandidate, guess: np.ndarray, what: str):
        """``record`` rejected when accepted but farther than ``loops.map_consistency_*`` from
        ``guess`` (``what`` names the prediction in the reason)."""
        cfg = self.config.loops
        dist_m, dyaw_deg = _se2_distance(guess, record.candidate_from_query)
        if record.accepted and (
            dist_m > cfg.map_consistency_m or dyaw_deg > cfg.map_consistency_deg
        ):
            reason = f"{dist_m:.1f} m / {dyaw_deg:.0f} deg from {what}"
            return replace(record, accepted=False, reason=reason)
        return record

    def _confirm_vote(self, session: _Session, vote: _PendingLoop) -> None:
        """A vote between two groups that linked nothing: check the placement it predicts at
        the session's earlier key frames now, and at its later ones as they come (see
        ``loops.confirm_*``)."""
        cfg = self.config.loops
        if not cfg.confirm_max_checks or cfg.proximity_radius_m is None:
            return
        if not vote.record.constraint_ratio >= cfg.confirm_min_constraint_ratio:
            return  # a slide along a straight street would be confirmed along it
        query = self._kf_by_key[vote.record.query]
        hyp = _Confirmation(vote, taken=[self._pose_in_group(query)[:2, 3]])
        self._confirming.append(hyp)
        # Nearest in time first: the overlap that produced the vote extends around it.
        for kf in reversed(session.key_frames[: query.key.index]):
            if self._check_confirmation(hyp, kf) is not None:
                break

    def _confirm_with(self, kf: KeyFrame) -> None:
        """A new key frame checks the open confirmations of its session's lone votes."""
        for hyp in list(self._confirming):
            if hyp.vote.record.query.session == kf.key.session:
                self._check_confirmation(hyp, kf)

    def _check_confirmation(self, hyp: _Confirmation, kf: KeyFrame) -> bool | None:
        """Register ``kf`` from the placement ``hyp``'s vote predicts, if it lies apart from
        the key frames already used and near the other group; then settle ``hyp`` when it can
        be: True (linked), False (given up), None (still open)."""
        cfg = self.config.loops
        rec = hyp.vote.record
        a = self.sessions[rec.query.session].group
        b = self.sessions[rec.candidate.session].group
        if a == b:  # linked by other loops meanwhile; the catch-up searches these key frames
            return self._settle(hyp)
        pose_a = self._pose_in_group(kf)
        if min(np.hypot(*(pose_a[:2, 3] - xy)) for xy in hyp.taken) < cfg.confirm_spacing_m:
            return None
        pose_b = self._b_from_a(hyp.vote, a) @ pose_a
        found = self._near_key_frames(self.groups[b], pose_b[:2, 3])
        if not found:
            return None
        other = found[0][1]
        hyp.taken.append(pose_a[:2, 3])
        guess = invert(self._pose_in_group(other)) @ pose_b
        cand_past = self._cand_past(guess)
        record, ver = self.confirmation_verifier.verify_candidate(
            kf.key,
            other.key,
            kf.timestamp_us,
            other.timestamp_us,
            float("nan"),
            self._local_map(kf, past_only=True),
            self._local_map(other, past_only=cand_past),
            guess,
            cache_keys=(self._map_key(kf, True), self._map_key(other, cand_past)),
        )
        record = self._near_prediction(
            replace(record, source="confirmation"), guess, "the vote's prediction"
        )
        if record.accepted and not record.constraint_ratio >= cfg.confirm_min_constraint_ratio:
            record = replace(
                record,
                accepted=False,
                reason=f"constraint_ratio {record.constraint_ratio:.2f} < "
                f"{cfg.confirm_min_constraint_ratio} (loops.confirm_min_constraint_ratio)",
            )
        if record.accepted:
            hyp.confirmed.append(_PendingLoop(record, ver.information))
        else:
            self.loops.append(record)
        hyp.checks += 1
        if len(hyp.confirmed) >= cfg.confirm_min_loops or hyp.checks == cfg.confirm_max_checks:
            return self._settle(hyp)
        return None

    def _settle(self, hyp: _Confirmation) -> bool:
        """Close a confirmation: with enough loops they join the votes and the groups link
        (True); otherwise, or when other loops linked the groups meanwhile, they are logged as
        rejected (False)."""
        cfg = self.config.loops
        self._confirming.remove(hyp)
        rec = hyp.vote.record

        def linked() -> bool:
            return (
                self.sessions[rec.query.session].group == self.sessions[rec.candidate.session].group
            )

        reason = "the sessions were linked by other loops meanwhile"
        if not linked():
            reason = (
                f"{len(hyp.confirmed)} of {hyp.checks} confirmations of a link vote "
                f"(need {cfg.confirm_min_loops} that agree)"
            )
            if len(hyp.confirmed) >= cfg.confirm_min_loops:
                self._votes.extend(hyp.confirmed)
                # before the merge: its catch-up need not search these key frames again
                closing = {p.record.query for p in hyp.confirmed} - self._closed
                self._closed |= closing
                self._try_merge(
                    self.sessions[rec.query.session].group,
                    self.sessions[rec.candidate.session].group,
                )
                if linked():
                    return True
                self._closed -= closing
                for p in hyp.confirmed:  # they disagreed with the vote after all
                    self._votes.remove(p)
                reason = "the confirmations disagree with the vote"
        for p in hyp.confirmed:
            self.loops.append(replace(p.record, accepted=False, reason=reason))
        return False

    def _weak(self, record: LoopCandidate) -> bool:
        """Whether a rejected global registration is a weak vote (``loops.weak_vote_*``)."""
        cfg = self.config.loops
        lv = self.config.backend.loop_verification
        if cfg.weak_vote_min_tight_fitness is None:
            return False
        return bool(
            record.fitness >= lv.min_fitness
            and record.overlap >= lv.min_overlap
            and record.inlier_rmse_m <= cfg.weak_vote_max_inlier_rmse_m
            and record.tight_fitness >= cfg.weak_vote_min_tight_fitness
            and record.constraint_ratio >= cfg.weak_vote_min_constraint_ratio
        )

    def _add_loop(self, record: LoopCandidate, information: np.ndarray) -> None:
        self.graph.add_loop(
            record.candidate, record.query, record.candidate_from_query, information
        )
        self.loop_information[(record.candidate, record.query)] = information
        self.loops.append(record)

    def _b_from_a(self, vote: _PendingLoop, a: int) -> np.ndarray:
        """Where a vote between groups ``a`` and another puts ``a`` in the other's frame."""
        rec = vote.record
        q, c = self._kf_by_key[rec.query], self._kf_by_key[rec.candidate]
        other_from_query_group = (
            self._pose_in_group(c) @ rec.candidate_from_query @ invert(self._pose_in_group(q))
        )
        if self.sessions[rec.query.session].group == a:
            return other_from_query_group
        return invert(other_from_query_group)

    def _side(self, vote: _PendingLoop, group: int) -> KeyFrame:
        """The key frame of a vote between two groups that lies in ``group``."""
        rec = vote.record
        key = rec.query if self.sessions[rec.query.session].group == group else rec.candidate
        return self._kf_by_key[key]

    def _try_merge(self, a: int, b: int) -> None:
        """Merge groups ``a`` and ``b`` once enough votes between them agree on their relative
        placement (the largest consistent set wins; the others are rejected as false loops)."""
        cfg = self.config.loops
        groups_of = {a, b}
        votes = [
            v
            for v in self._votes
            if {self.sessions[v.record.query.session].group,
                self.sessions[v.record.candidate.session].group} == groups_of
        ]  # fmt: skip
        placements = [self._b_from_a(v, a) for v in votes]
        # Where each vote's key frame on side a lies in a's frame: two placements are compared
        # where the loops are, not at a's origin, which may be hundreds of metres away (a
        # 0.5 deg difference there is metres of translation, and it would hide a slide along a
        # street of the same size).
        at = [self._pose_in_group(self._side(v, a))[:2, 3] for v in votes]

        def agree_on(i: int, j: int) -> bool:
            t_i, t_j = placements[i], placements[j]
            moved = max(
                float(np.hypot(*((t_i[:2, :2] - t_j[:2, :2]) @ x + t_i[:2, 3] - t_j[:2, 3])))
                for x in (at[i], at[j])
            )
            dyaw = abs(_se2_distance(t_i, t_j)[1])
            return moved <= cfg.link_consistency_m and dyaw <= cfg.link_consistency_deg

        def strength(agree: list[int]) -> tuple[int, int]:
            return sum(not votes[j].weak for j in agree), len(agree)

        best: list[int] = []
        for i in range(len(votes)):
            agree = [j for j in range(len(votes)) if agree_on(i, j)]
            if strength(agree) > strength(best):
                best = agree
        strong, total = strength(best)
        weak_link = (
            cfg.weak_vote_min_tight_fitness is not None
            and strong >= 1
            and total >= cfg.weak_link_min_votes
        )
        if strong < cfg.link_min_consistent_loops and not weak_link:
            return
        b_from_a = _se2_mean([placements[j] for j in best])  # each vote errs independently
        agreeing = {id(votes[j]) for j in best}
        links = []
        for v in votes:
            self._votes.remove(v)
            if id(v) in agreeing:
                if v.weak:  # loops.csv shows its tight fitness / RMSE past the thresholds
                    v = replace(v, record=replace(v.record, accepted=True, reason="ok"))
                links.append(v)
            elif v.weak:
                self.loops.append(v.record)
            else:
                self.loops.append(
                    replace(v.record, accepted=False, reason="inconsistent with the session link")
                )
        self._merge(a, b, b_from_a, links)

    def _merge(self, a: int, b: int, b_from_a: np.ndarray, links: list[_PendingLoop]) -> None:
        ga, gb = self.groups[a], self.groups[b]
        if ga.in_map or (not gb.in_map and len(ga.from_session) > len(gb.from_session)):
            ga, gb, b_from_a = gb, ga, invert(b_from_a)  # keep the map's (or larger) frame
        del self.groups[ga.index]
        moved = list(ga.from_session)
        for name, group_from_session in ga.from_session.items():
            gb.from_session[name] = b_from_a @ group_from_session
            self.sessions[name].group = gb.index
        loops = ga.loops + links
        stayed = [n for n in gb.from_session if n not in ga.from_session]
        if gb.in_map:
            for name in moved:
                self._insert_session(self.sessions[name], gb.from_session[name], "unknown")
            for p in loops:
                self._add_loop(p.record, p.information)
        else:
            gb.loops.extend(loops)
        self._catch_up(moved, stayed)

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
                    if kf.key in self._closed:
                        continue
                    for other in self._proximity_candidates(session, kf, among=earlier):
                        self._verify(session, kf, other, float("nan"), self.proximity_verifier)

    def _insert_group(self, group: _Group, anchor: str) -> None:
        """Put every session of a group into the graph (the first with ``anchor``) and its
        loops; a group outside the map becomes its own component."""
        for k, name in enumerate(group.from_session):
            self._insert_session(
                self.sessions[name], group.from_session[name], anchor if k == 0 else "unknown"
            )
        for p in group.loops:
            self._add_loop(p.record, p.information)
        group.loops = []

    def _insert_session(self, session: _Session, world_from_session: np.ndarray, anchor: str):
        """Put a session's odometry chain into the graph at ``world_from_session``."""
        kfs = session.key_frames
        if not kfs:
            return
        self.graph.add_session(session.name, world_from_session @ kfs[0].odometry_pose, anchor)
        session.inserted = True
        session.world_from_session = world_from_session
        for kf in kfs[1:]:
            self._add_node(session, kf)

    def key_frames(self, session: str) -> list[KeyFrame]:
        return list(self.sessions[session].key_frames)

    def session_placement(self, session: str) -> np.ndarray | None:
        """world_from_session used to insert the session's odometry chain (None: not inserted)."""
        return self.sessions[session].world_from_session

    def _dpr_mask(self):
        if self.recognizer is None:
            from radarslam.place_recognition.config import DPRConfig
            from radarslam.place_recognition.dpr import make_point_mask

            return make_point_mask(DPRConfig())
        from radarslam.place_recognition.dpr import make_point_mask

        return make_point_mask(self.recognizer.config.dpr)

    def _result(self) -> SlamResult:
        from radarslam.slam.map import StaticMapBuilder
        from radarslam.slam.outputs import SessionResult

        estimate = self.graph.estimate()
        sessions = []
        builder = StaticMapBuilder(self.config.backend.static_map)
        for s in self.sessions.values():
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
        has_points = any(len(kf.cloud_points) for kf in self._kf_by_key.values())
        static_map = builder.build() if has_points else None
        return SlamResult(
            sessions=sessions,
            loops=list(self.loops),
            components=self.graph.components(),
            static_map=static_map,
            timings=self.timings,
            duration_s=self._duration_s,
            graph=self.graph,
        )

    def _progress_bar(self, infos: Sequence[SceneInfo]):
        if not self.progress:
            return None
        from tqdm import tqdm

        ref = self.config.key_frames.ref_channel
        total = sum(len(self.reader.sweep_tokens(i, ref)) for i in infos)
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
