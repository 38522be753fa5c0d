"""The front-end feed: radar frames -> odometry -> key-frame clouds, as typed messages.

:class:`OdometryFeed` runs the odometry over every frame of the scenes and yields what the
key-frame side needs: :class:`SessionStart`, :class:`KeyFrameReady`, :class:`FramesRead` and
:class:`SessionSpan`. Nothing it reads is written by the key-frame side (odometry never depends
on loops), so with :meth:`OdometryFeed.run_forked` it runs in a forked process fed by a second
one that reads the radar data, and the messages cross a queue: on two cores the odometry and the
key-frame work (recognition, registration, iSAM2) overlap, with identical results.
"""

from __future__ import annotations

import itertools
import logging
import os
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from radarslam.errors import DataError
from radarslam.slam.processes import (
    REAP_EVERY_S,
    Failed,
    end_helper,
    helper_process_setup,
    one_torch_thread,
    put_error,
)
from radarslam.types import AccumulatedCloud, SceneInfo

log = logging.getLogger("radarslam.odometry")

# --- messages ------------------------------------------------------------------------------------


@dataclass(frozen=True)
class KeyFrameInput:
    """What the key-frame side needs of a key frame's frame and odometry result."""

    timestamp_us: int
    sample_token: str
    gt_pose: np.ndarray
    odometry_pose: np.ndarray
    motion: np.ndarray | None  # key-frame motion from the odometry (None: it restarted)
    motion_cov: np.ndarray | None
    ego_from_ref: np.ndarray


def key_frame_input(frame, res, buffer) -> KeyFrameInput:
    def copy(a):
        return None if a is None else np.array(a, dtype=np.float64)

    return KeyFrameInput(
        timestamp_us=int(frame.timestamp_us),
        sample_token=frame.sample_token,
        gt_pose=np.array(frame.world_from_ego, dtype=np.float64),
        odometry_pose=np.array(res.world_from_ego, dtype=np.float64),
        motion=copy(res.key_frame_motion),
        motion_cov=copy(res.key_frame_covariance),
        ego_from_ref=np.array(buffer.ego_from_ref(), dtype=np.float64),
    )


@dataclass(frozen=True)
class SessionStart:
    """The frames that follow belong to the scene ``name``, a new session; ``continues`` names
    the session whose odometry it continues (``SlamConfig.continue_log_scenes``), else None."""

    name: str
    continues: str | None = None


@dataclass(frozen=True)
class KeyFrameReady:
    """A key frame of ``session``: its odometry and its accumulated cloud."""

    session: str
    frame: KeyFrameInput
    cloud: AccumulatedCloud


@dataclass(frozen=True)
class FramesRead:
    """``count`` more frames went through the odometry (for the progress bar)."""

    count: int


@dataclass(frozen=True)
class SessionSpan:
    """Sensor time covered by the session just ended."""

    first_us: int
    last_us: int


#: What the key-frame side receives.
FeedMessage = SessionStart | KeyFrameReady | FramesRead | SessionSpan


@dataclass(frozen=True)
class FrameBatch:
    """Reading process -> odometry process: the next frames of the current scene."""

    frames: list


@dataclass(frozen=True)
class SceneEnd:
    """Reading process -> odometry process: the scene ``name`` has no more frames."""

    name: str


@dataclass(frozen=True)
class ReadingDone:
    """Reading process -> odometry process: every scene read, in ``data_s`` seconds."""

    data_s: float


@dataclass(frozen=True)
class OdometryDone:
    """Odometry process -> key-frame side: the odometry's timings (:data:`TIMING_FIELDS`) and
    its Doppler calibration at the end of the run (``DopplerCalibration.as_dict()``), and
    every radar rig's."""

    timings: dict[str, Any]
    calibration: dict | None = None
    calibrations: list[dict] = field(default_factory=list)


#: The timings the odometry side measures (the rest are the key-frame side's).
TIMING_FIELDS = ("data_s", "odometry_s", "key_frame_s", "frames")


# --- the odometry side ---------------------------------------------------------------------------


def drives_on(info: SceneInfo, previous: tuple[SceneInfo, int] | None, first, max_gap_us) -> bool:
    """Whether the scene ``info``, whose first frame is ``first`` (None: it has none), continues
    the drive of ``previous`` (the scene read just before it, with its last frame's time): cut
    from the same log, starting within ``max_gap_us`` of that scene's end. Consecutive nuScenes
    scenes may share their boundary key frame: a start up to ``max_gap_us`` before that end
    counts too, and :func:`after` drops the frames already driven."""
    if first is None or previous is None or not info.log_token:
        return False
    before, last_us = previous
    return info.log_token == before.log_token and abs(first.timestamp_us - last_us) <= max_gap_us


def after(frames: Iterable, last_us: int | None) -> Iterator:
    """``frames`` from the first one later than ``last_us`` (None: all of them)."""
    if last_us is None:
        return iter(frames)
    return itertools.dropwhile(lambda f: f.timestamp_us <= last_us, frames)


@dataclass
class SceneDrive:
    """One scene as the odometry drives it: ``frames`` (those not driven already), the session
    it ``continues`` (None: it starts a drive), and the time of the last frame driven so far."""

    info: SceneInfo
    continues: str | None
    frames: Iterator[Any]
    last_us: int | None = None


def scene_drives(
    infos: Sequence[SceneInfo], read: Callable, max_gap_us: float, continue_log_scenes: bool
) -> Iterator[SceneDrive]:
    """The scenes in order, each continuing the one before it where :func:`drives_on` says so
    (with ``continue_log_scenes``); ``read(info)`` gives a scene's frames. A drive's frames
    must be consumed before the next one is asked for: its end decides the next one."""
    previous: tuple[SceneInfo, int] | None = None  # the last scene with frames, its end

    def recorded(frames: Iterator, drive: SceneDrive) -> Iterator:
        for frame in frames:
            drive.last_us = frame.timestamp_us
            yield frame

    for info in infos:
        frames = iter(read(info))
        first = next(frames, None)
        drive = SceneDrive(info, None, iter(()))
        if first is not None:
            todo: Iterator[Any] = itertools.chain([first], frames)
            if continue_log_scenes and drives_on(info, previous, first, max_gap_us):
                assert previous is not None
                drive.continues = previous[0].name
                todo = after(todo, previous[1])  # frames the scene before drove already
            drive.frames = recorded(todo, drive)
        yield drive
        previous = (info, drive.last_us) if drive.last_us is not None else None


class OdometryFeed:
    """Odometry over every frame of the scenes, as :data:`FeedMessage` s.

    ``odometry`` is reset for every scene but one that continues the scene before it
    (``config.continue_log_scenes``); the session processed first may start on its ground
    truth (``config.first_session_anchor``), later ones start unknown. ``point_mask`` makes the
    key-frame clouds' dynamic-point mask (called per scene, only when
    ``key_frames.dynamic_points`` is not ``odometry``). The odometry's timings go to ``timings``.
    """

    def __init__(self, reader, config, odometry, frame_filter, timings, point_mask: Callable):
        self.reader = reader
        self.config = config
        self.odometry = odometry
        self.frame_filter = frame_filter
        self.timings = timings
        self.point_mask = point_mask
        #: The odometry's Doppler calibration once every scene has run (the run's estimate).
        self.calibration: dict | None = None
        #: Every radar rig's (several when the scenes come from several vehicles).
        self.calibrations: list[dict] = []

    def messages(
        self, infos: Sequence[SceneInfo], frames: Callable | None = None
    ) -> Iterator[FeedMessage]:
        """The messages of every scene in order. ``frames(info)`` gives a scene's frames (None:
        read them here)."""
        from radarslam.odometry.calibration import mounting_rotations, with_mounting
        from radarslam.odometry.run import DopplerHealth
        from radarslam.slam.keyframes import SweepBuffer

        own_reading = frames is None

        def read(info: SceneInfo):
            if frames is not None:
                return frames(info)
            return self.reader.iter_frames(info, filters=self.frame_filter)

        cfg = self.config
        timings = self.timings
        # The key-frame clouds take one calibration for every session (the configured one, or
        # with ``cloud_calibration: applied`` that plus a calibration pass's estimate), never the
        # estimate the odometry folds in at each session: loops register one session's clouds
        # against another's, and clouds turned by different estimates disagree (turned per
        # session, the benchmark's clouds linked 2 of 8 sessions instead of 8).
        cloud_mounting = mounting_rotations(
            self.odometry.config.mounting_yaw_deg
            if cfg.key_frames.cloud_calibration == "applied"
            else cfg.odometry.mounting_yaw_deg
        )
        use_odometry_mask = cfg.key_frames.dynamic_points == "odometry"
        buffer = None
        drives = scene_drives(
            infos,
            read,
            self.odometry.config.fusion.max_gap_s * 1e6,
            cfg.continue_log_scenes,
        )
        for n in itertools.count():
            t_data = time.perf_counter()
            drive = next(drives, None)  # reads the scene's first frame
            if drive is None:
                break
            if own_reading:
                timings.data_s += time.perf_counter() - t_data
            info = drive.info
            yield SessionStart(info.name, drive.continues)
            if drive.continues is not None:  # the odometry and the sweep buffer drive on
                self.odometry.fold_calibration()
            else:
                self.odometry.config.initial_pose = (
                    cfg.first_session_anchor if n == 0 else "identity"
                )
                self.odometry.reset()
                buffer = SweepBuffer(
                    nsweeps=cfg.key_frames.nsweeps,
                    ref_channel=cfg.key_frames.ref_channel,
                    min_distance_m=cfg.key_frames.min_distance_m,
                    point_mask=self.point_mask() if not use_odometry_mask else None,
                )
            assert buffer is not None
            span = None
            health = DopplerHealth(self.odometry.config.doppler.min_points)
            pending = 0  # frames not yet reported to the progress bar
            t_data = time.perf_counter()
            for frame in drive.frames:
                t0 = time.perf_counter()
                if own_reading:  # else the reading process reports its own time
                    timings.data_s += t0 - t_data
                res = self.odometry.process(frame)
                health.add(res.doppler)
                t1 = time.perf_counter()
                timings.odometry_s += t1 - t0
                timings.frames += 1
                span = (frame.timestamp_us if span is None else span[0], frame.timestamp_us)
                twist = res.doppler.twist if res.doppler.valid else np.zeros(3)
                masks = res.doppler.static_masks if use_odometry_mask else None
                buffer.add_frame(
                    with_mounting(frame, cloud_mounting), res.world_from_ego, twist, masks
                )
                pending += 1
                if res.is_key_frame:
                    t2 = time.perf_counter()
                    cloud = buffer.accumulate(
                        frame.timestamp_us, res.world_from_ego, frame.sample_token
                    )
                    timings.key_frame_s += time.perf_counter() - t2
                    if cloud is not None:  # None before the reference radar has been seen
                        yield FramesRead(pending)
                        pending = 0
                        yield KeyFrameReady(info.name, key_frame_input(frame, res, buffer), cloud)
                t_data = time.perf_counter()
            if pending:
                yield FramesRead(pending)
            why = health.problem()
            if why is not None:
                log.warning("scene %s: %s: its odometry is unreliable", info.name, why)
            if span is not None:
                yield SessionSpan(span[0], span[1])
        self.calibration = self.odometry.calibration.as_dict()
        self.calibrations = [c.as_dict() for c in self.odometry.calibrations]

    def run_forked(
        self,
        infos: Sequence[SceneInfo],
        handle: Callable[[FeedMessage], None],
        meanwhile: Callable[[], None] = lambda: None,
    ) -> None:
        """:meth:`messages` in a forked process, fed by a second one that reads the radar data;
        each message is given to ``handle`` here, in order. ``meanwhile`` runs here once the
        helpers have started (the recognizer's loading). Threads would not do: open3d's and
        kiss-icp's bindings hold the GIL (measured: no gain). torch gets one thread until the
        odometry is done, then both cores for the queue's backlog. The two forked processes run
        at a lower priority (:data:`HELPER_NICENESS`) so that this side, the longest chain, is
        not left behind. A fourth process for AutoPlace's CNN measured no faster on 2 cores:
        identical results, 2.5 s more work (torch and the weights loaded twice)."""
        import multiprocessing as mp

        from radarslam.io.atomic import interrupts_deferred

        ctx = mp.get_context("fork")
        # Room for about 250 key frames (~40 MB): the key-frame side's work comes in bursts
        # (sessions linking, catch-up searches), and a short queue would stall the odometry
        # meanwhile, leaving a core idle later.
        messages = ctx.Queue(maxsize=512)
        # Reading (a sixth of the odometry process's work) in a third process: the odometry is
        # the longest chain, and the key-frame side has room to share a core with the reader.
        frames = ctx.Queue(maxsize=64)
        finished = ctx.Event()
        procs = {
            "radar reading": ctx.Process(
                target=_reading_process,
                args=(self.reader, infos, self.frame_filter, frames, os.getpid()),
                name="slam-reading",
            ),
            "odometry": ctx.Process(
                target=_odometry_process,
                args=(self, infos, messages, finished, os.getpid(), frames),
                name="slam-odometry",
            ),
        }
        try:
            for proc in procs.values():
                proc.daemon = True
                # Ctrl-C inside fork()'s at-fork handlers would be printed as "Exception
                # ignored" and lost: it waits until the helper runs
                with interrupts_deferred():
                    proc.start()
            meanwhile()
            with one_torch_thread() as all_threads:
                self._consume(infos, handle, procs, messages, finished, all_threads)
            for proc in procs.values():
                proc.join()
        finally:
            for proc in procs.values():
                end_helper(proc, stop_now=True)

    def _consume(self, infos, handle, procs, messages, finished, all_threads) -> None:
        """Hand the odometry process's messages to ``handle`` until :class:`OdometryDone`."""
        import queue as queue_mod

        reap_at = time.monotonic() + REAP_EVERY_S
        while True:
            if time.monotonic() >= reap_at:
                # is_alive() collects a helper that has ended (the reader, seconds before the
                # odometry): were this process killed meanwhile, it would be left to init.
                for proc in procs.values():
                    proc.is_alive()
                reap_at = time.monotonic() + REAP_EVERY_S
            try:
                message = messages.get(timeout=REAP_EVERY_S)
            except queue_mod.Empty:
                for what, proc in procs.items():
                    # the reader may be done (exit code 0) long before the odometry
                    if not proc.is_alive() and (proc.exitcode != 0 or what == "odometry"):
                        raise DataError(
                            f"the {what} process ended without finishing "
                            f"(exit code {proc.exitcode}; scenes {infos[0].name}..)"
                        ) from None
                continue
            if isinstance(message, Failed):
                raise message.error
            if isinstance(message, OdometryDone):
                for name, value in message.timings.items():
                    setattr(self.timings, name, value)
                self.calibration = message.calibration
                self.calibrations = message.calibrations
                break
            if finished.is_set():
                all_threads()
            handle(message)


# --- the calibration pass ------------------------------------------------------------------------


#: Frames per message from the reading process: one queue round trip per frame costs more than
#: the frame's pickle.
_FRAME_BATCH = 16


def _reading_process(reader, infos, filters, frames, parent: int) -> None:
    """Body of the forked reading process: every scene's frames in :class:`FrameBatch` es, then
    :class:`SceneEnd`; after the last scene :class:`ReadingDone`."""
    try:
        helper_process_setup(parent)
        data_s = 0.0
        for info in infos:
            batch = []
            t0 = time.perf_counter()
            for frame in reader.iter_frames(info, filters=filters):
                batch.append(frame)
                if len(batch) == _FRAME_BATCH:
                    data_s += time.perf_counter() - t0
                    frames.put(FrameBatch(batch))
                    batch = []
                    t0 = time.perf_counter()
            data_s += time.perf_counter() - t0
            if batch:
                frames.put(FrameBatch(batch))
            frames.put(SceneEnd(info.name))
        frames.put(ReadingDone(data_s))
    except BaseException as exc:  # handed to the odometry process, which raises it
        put_error(frames, exc, "reading process")
    finally:
        frames.close()
        frames.join_thread()


class _QueuedFrames:
    """The odometry process's frame source when a reading process reads: the frames of each
    scene from its queue, in order; the reading time it reports becomes ``data_s``."""

    def __init__(self, frames, timings):
        self._frames, self._timings = frames, timings

    def __call__(self, info: SceneInfo):
        while True:
            message = self._frames.get()
            if isinstance(message, FrameBatch):
                yield from message.frames
            elif isinstance(message, SceneEnd):
                if message.name != info.name:  # a programming error, not a data problem
                    raise AssertionError(f"reading process sent {message.name}, not {info.name}")
                return
            elif isinstance(message, Failed):
                raise message.error
            else:
                raise AssertionError(f"unexpected message {message!r} from the reading process")

    def finish(self) -> None:
        """After the last scene: the reading time."""
        message = self._frames.get()
        if isinstance(message, Failed):
            raise message.error
        if not isinstance(message, ReadingDone):
            raise AssertionError(f"unexpected message {message!r} from the reading process")
        self._timings.data_s = message.data_s


def _odometry_process(feed, infos, messages, finished, parent: int, frames=None) -> None:
    """Body of the forked odometry process: stream messages, then :class:`OdometryDone` (or
    :class:`Failed`); ``finished`` (an Event) is set once the work is done and only the queue is
    left. ``frames``: the queue of a reading process (None: read here)."""
    try:
        helper_process_setup(parent)
        source = None if frames is None else _QueuedFrames(frames, feed.timings)
        for message in feed.messages(infos, source):
            messages.put(message)
        if source is not None:
            source.finish()
        finished.set()
        t = feed.timings
        messages.put(
            OdometryDone(
                {name: getattr(t, name) for name in TIMING_FIELDS},
                feed.calibration,
                feed.calibrations,
            )
        )
    except BaseException as exc:  # handed to the parent, which raises it
        put_error(messages, exc, "odometry process")
    finally:
        messages.close()
        messages.join_thread()
