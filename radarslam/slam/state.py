"""What the key-frame side knows of the run: sessions, their key frames, and the groups that
place sessions relative to each other (:class:`MapState`), with the geometry every part of it
reads: a key frame's pose in its group, its local map, the key frames near a position."""

from __future__ import annotations

import bisect
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from radarslam.geometry import invert
from radarslam.io.loops import LoopCandidate, NodeKey
from radarslam.types import AccumulatedCloud

if TYPE_CHECKING:
    from radarslam.slam.config import SlamConfig
    from radarslam.slam.pose_graph import PoseGraph

#: Odometry covariance (x, y, yaw) used where the odometry chain broke (a long gap in the data).
BROKEN_CHAIN_SIGMAS = np.array([10.0, 10.0, 0.5])


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
    #: the previous key frame when it is another session's (a continued session's first key
    #: frame): ``relative`` moves from it
    follows: NodeKey | None = None


@dataclass
class PendingLoop:
    """A verified loop not yet in the graph."""

    record: LoopCandidate
    information: np.ndarray


@dataclass
class Group:
    """Sessions placed relative to each other by consistent loops; ``in_map`` for the group of
    the anchored session, the one processed first (its frame is the world)."""

    index: int
    from_session: dict[str, np.ndarray] = field(default_factory=dict)  # group_from_session
    in_map: bool = False
    loops: list[PendingLoop] = field(default_factory=list)  # inside the group, not in the graph


@dataclass
class Session:
    name: str
    index: int
    group: int = -1
    key_frames: list[KeyFrame] = field(default_factory=list)
    inserted: bool = False
    world_from_session: np.ndarray | None = None  # where the chain was put in the map
    last_loop_kf: int = -(10**9)
    last_reversed_kf: int = -(10**9)  # the last key frame that ran the turned search
    last_merge_kf: int = -(10**9)  # the last key frame that searched the other groups
    timestamps_us: list[int] = field(default_factory=list)  # of the key frames, increasing
    #: the dataset log (one vehicle's one drive) the scene was cut from; "" when unknown
    log: str = ""
    #: the session whose odometry this one continues (``SlamConfig.continue_log_scenes``)
    continues: str | None = None
    #: the first session of the drive it belongs to (itself unless it continues one): a pass
    drive: str = ""
    _xy: np.ndarray = field(default_factory=lambda: np.zeros((64, 2)))  # grows by doubling

    def add_position(self, xy: np.ndarray) -> None:
        n = len(self.timestamps_us) - 1  # the key frame's index (its timestamp is in already)
        if n >= len(self._xy):
            self._xy = np.concatenate([self._xy, np.zeros_like(self._xy)])
        self._xy[n] = xy

    def positions(self) -> np.ndarray:
        """(N, 2) odometry positions of the key frames so far (a view, no copy)."""
        return self._xy[: len(self.timestamps_us)]


def make_key_frame(
    session: Session, inp, cloud: AccumulatedCloud, prev: KeyFrame | None = None
) -> KeyFrame:
    """The session's next key frame from the feed's :class:`~radarslam.slam.feed.KeyFrameInput`
    and its accumulated cloud. ``prev``: the key frame its odometry motion starts from (default:
    the session's last; :meth:`MapState.previous_key_frame`)."""
    ego_from_ref = inp.ego_from_ref
    xy_ref = np.column_stack([cloud.points["x"], cloud.points["y"]])
    xy_ego = xy_ref @ ego_from_ref[:2, :2].T + ego_from_ref[:2, 3]
    if prev is None and session.key_frames:
        prev = session.key_frames[-1]
    kf = KeyFrame(
        key=NodeKey(session.name, len(session.key_frames)),
        timestamp_us=inp.timestamp_us,
        sample_token=inp.sample_token,
        odometry_pose=inp.odometry_pose,
        gt_pose=inp.gt_pose,
        cloud_xy_ego=xy_ego,
        cloud_points=cloud.points,
        ego_from_ref=ego_from_ref,
    )
    if prev is not None:
        if prev.key.session != session.name:
            kf.follows = prev.key
        if inp.motion is not None:
            kf.relative = inp.motion
            kf.relative_cov = inp.motion_cov
        else:  # the odometry restarted (gap in the data): a weak link keeps the chain whole
            kf.relative = invert(prev.odometry_pose) @ kf.odometry_pose
            kf.relative_cov = np.diag(np.square(BROKEN_CHAIN_SIGMAS))
    return kf


class MapState:
    """Sessions, groups and key frames of a run, and the log of every loop candidate decided.

    ``graph`` is the pose graph (a session's poses come from it once the session is inserted);
    ``config`` the :class:`~radarslam.slam.config.SlamConfig`, read when used."""

    def __init__(self, config: SlamConfig, graph: PoseGraph) -> None:
        self.config = config
        self.graph = graph
        self.sessions: dict[str, Session] = {}
        self.groups: dict[int, Group] = {}
        #: Every candidate decided so far, accepted or not, in the order decided.
        self.loops: list[LoopCandidate] = []
        self._kf_by_key: dict[NodeKey, KeyFrame] = {}

    # --- building --------------------------------------------------------------------------------

    def start_session(self, name: str, log: str = "", continues: str | None = None) -> Session:
        """A new session in a group of its own, or, when it ``continues`` an earlier session's
        odometry, in that session's group, placed in the same odometry frame."""
        if continues is not None and continues not in self.sessions:
            raise ValueError(f"session {name!r} continues {continues!r}, which has not started")
        session = Session(name, len(self.sessions), log=log, continues=continues)
        session.drive = self.sessions[continues].drive if continues is not None else name
        self.sessions[name] = session
        if continues is not None:
            group = self.groups[self.sessions[continues].group]
            group.from_session[name] = group.from_session[continues].copy()
        else:
            group = Group(session.index, {name: np.eye(4)})  # unique: merges delete groups
            self.groups[group.index] = group
        session.group = group.index
        return session

    def previous_key_frame(self, session: Session) -> KeyFrame | None:
        """The key frame the session's next key frame moves from: its last one, or, before its
        first, the last key frame of the session it continues (None: it starts a chain)."""
        if session.key_frames:
            return session.key_frames[-1]
        if session.continues is not None:
            return self.previous_key_frame(self.sessions[session.continues])
        return None

    def add(self, kf: KeyFrame) -> None:
        """Append ``kf`` to its session (it must be the session's next key frame)."""
        session = self.sessions[kf.key.session]
        session.key_frames.append(kf)
        session.timestamps_us.append(kf.timestamp_us)
        session.add_position(kf.odometry_pose[:2, 3])
        self._kf_by_key[kf.key] = kf

    # --- reading ---------------------------------------------------------------------------------

    def key_frame(self, key: NodeKey) -> KeyFrame:
        return self._kf_by_key[key]

    def all_key_frames(self):
        return self._kf_by_key.values()

    def group_of(self, key: NodeKey) -> int:
        return self.sessions[key.session].group

    def pose_in_group(self, kf: KeyFrame) -> np.ndarray:
        """The key frame's pose in its group's frame (the graph's estimate once in the map)."""
        session = self.sessions[kf.key.session]
        if session.inserted:
            return self.graph.current_pose(kf.key)
        return self.groups[session.group].from_session[session.name] @ kf.odometry_pose

    def near_key_frames(
        self,
        group: Group,
        xy: np.ndarray,
        among: set[str] | None = None,
        recent_of: KeyFrame | None = None,
    ) -> list[tuple[float, KeyFrame]]:
        """(distance, key frame) of the group's key frames within ``proximity_radius_m`` of
        ``xy`` (group frame, key frames placed by link @ odometry), nearest first, at most one
        per session (of the sessions ``among``, if given; ``recent_of``'s recent past left out,
        in its session and those of its drive)."""
        cfg = self.config.loops
        drive = self.sessions[recent_of.key.session].drive if recent_of is not None else None
        found: list[tuple[float, KeyFrame]] = []
        for name, group_from_session in group.from_session.items():
            if among is not None and name not in among:
                continue
            other = self.sessions[name]
            pos = other.positions()
            if recent_of is not None and other.drive == drive:
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

    def excluded(self, kf: KeyFrame) -> Callable[[NodeKey], bool]:
        """Keys a query may not return: the recent past of its own pass (its session and the
        sessions whose drive it continues)."""
        recent_us = self.config.loops.exclude_recent_s * 1e6
        drive = self.sessions[kf.key.session].drive

        def skip(key: NodeKey) -> bool:
            if self.sessions[key.session].drive != drive:
                return False
            return kf.timestamp_us - self._kf_by_key[key].timestamp_us < recent_us

        return skip

    def cloud_of(self, kf: KeyFrame) -> AccumulatedCloud:
        return AccumulatedCloud(
            points=kf.cloud_points,
            world_from_ref=kf.odometry_pose @ kf.ego_from_ref,
            ref_channel=self.config.key_frames.ref_channel,
            timestamp_us=kf.timestamp_us,
            sample_token=kf.sample_token,
        )

    def sequence(self, session: Session, cloud, seq_len: int) -> list[AccumulatedCloud]:
        """The clouds of a place-recognition sequence ending at the session's newest key frame,
        whose cloud is ``cloud``: its ``seq_len - 1`` predecessors, oldest first, then ``cloud``."""
        return [*(self.cloud_of(k) for k in session.key_frames[-seq_len:-1]), cloud]

    # --- local maps ------------------------------------------------------------------------------

    def window(self, kf: KeyFrame, past_only: bool) -> tuple[int, int]:
        """[lo, hi) of the key frames in ``kf``'s local map (its session's, so far)."""
        n = self.config.key_frames.local_map_neighbors
        frames = self.sessions[kf.key.session].key_frames
        lo = max(0, kf.key.index - n)
        hi = kf.key.index + 1 if past_only else min(len(frames), kf.key.index + n + 1)
        return lo, hi

    def map_key(self, kf: KeyFrame, past_only: bool) -> tuple:
        """Names a local map's content for the verifiers' caches: odometry poses and clouds
        never change, so the key frame and its window determine the points."""
        return (kf.key, *self.window(kf, past_only))

    def local_map(self, kf: KeyFrame, past_only: bool) -> np.ndarray:
        """(N, 2) points of ``kf``'s local map in its ego frame: its session's key frames around
        it (``past_only``: up to it), placed by odometry."""
        frames = self.sessions[kf.key.session].key_frames
        lo, hi = self.window(kf, past_only)
        ego_from_world = invert(kf.odometry_pose)
        chunks = []
        for other in frames[lo:hi]:
            t = ego_from_world @ other.odometry_pose
            chunks.append(other.cloud_xy_ego @ t[:2, :2].T + t[:2, 3])
        return np.concatenate(chunks) if chunks else np.zeros((0, 2))
