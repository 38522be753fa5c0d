"""The calibration pass of a SLAM run (``odometry.fusion.calibration.passes: 2``): the odometry
over the scenes, in order, until the vehicle's mounting yaws are known to
``calibration_pass_max_sigma_deg``, in a forked process as the run's odometry is
(:mod:`radarslam.slam.processes`). The pipeline applies what it found from the run's first frame.
"""

from __future__ import annotations

import dataclasses
import functools
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from radarslam.errors import DataError
from radarslam.odometry.calibration import count_rigs
from radarslam.slam.feed import scene_drives
from radarslam.slam.processes import (
    REAP_EVERY_S,
    Failed,
    end_helper,
    helper_process_setup,
    put_error,
)
from radarslam.types import SceneInfo

#: How far a calibration pass may be from its sigma limit and still go on: it stops once the
#: scenes left, with the sigma shrinking as 1/sqrt(drive time), could not bring it below this
#: many times the limit. From the second scene on, the final sigma came out 0.65-1.3x that
#: projection on the demo, the city benchmark and subset, and the real Boston scenes.
PASS_PROJECTION_SLACK = 2.0


@dataclass(frozen=True)
class CalibrationPassResult:
    """What a calibration pass found: ``calibration`` (``DopplerCalibration.as_dict()``),
    whether every mounting yaw's sigma got below the limit, and over how many scenes."""

    calibration: dict
    converged: bool
    scenes_used: int
    scenes_total: int
    rigs: int = 1  # radar rigs (vehicles) among the scenes used

    @property
    def max_sigma_deg(self) -> float:
        return max(self.calibration.get("mounting_yaw_sigma_deg", {}).values(), default=np.nan)


def estimate_calibration(
    reader,
    infos,
    config,
    frame_filter,
    max_sigma_deg: float | None,
    progress: bool = False,
    continue_log_scenes: bool = True,
) -> CalibrationPassResult:
    """The odometry (``config``) over the scenes in order, each from a reset as in a SLAM run
    (with ``continue_log_scenes``, a scene that continues the one before it drives on),
    until every mounting yaw's sigma is below ``max_sigma_deg`` (None: every scene), on every
    ``fusion.calibration.pass_frame_stride``-th frame of each drive. From the second scene on
    it also stops once the key frames left could not get there (:data:`PASS_PROJECTION_SLACK`):
    a run of short scenes then does not pay for a pass it cannot use."""
    from radarslam.odometry.pipeline import RadarOdometry

    odometry = RadarOdometry(config)
    rigs = count_rigs(reader, infos)
    if rigs > 1:  # one set of mounting yaws cannot serve several cars: no pass
        return CalibrationPassResult(odometry.calibration.as_dict(), False, 0, len(infos), rigs)
    # key frames as the measure of drive time: known for every scene before it is read
    samples = np.cumsum([max(info.nbr_samples, 1) for info in infos])
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(infos), unit="scene", desc="calibration pass", leave=False)

    def result(used: int, converged: bool) -> CalibrationPassResult:
        return CalibrationPassResult(odometry.calibration.as_dict(), converged, used, len(infos))

    def read(info: SceneInfo):
        return reader.iter_frames(info, filters=frame_filter)

    drives = scene_drives(infos, read, config.fusion.max_gap_s * 1e6, continue_log_scenes)
    stride = config.fusion.calibration.pass_frame_stride
    driven = 0
    try:
        for i, drive in enumerate(drives):
            if drive.continues is not None:
                odometry.fold_calibration()
            else:
                odometry.reset()
                driven = 0  # frames of this drive so far: a continued scene keeps the stride
            for frame in drive.frames:
                if driven % stride == 0:
                    odometry.process(frame)
                driven += 1
            if bar is not None:
                bar.update(1)
            if max_sigma_deg is None:
                continue
            found = result(i + 1, False)
            if found.max_sigma_deg < max_sigma_deg:
                return dataclasses.replace(found, converged=True)
            projected = found.max_sigma_deg * np.sqrt(samples[i] / samples[-1])
            if i >= 1 and projected > PASS_PROJECTION_SLACK * max_sigma_deg:
                return found
    finally:
        if bar is not None:
            bar.close()
    return result(len(infos), max_sigma_deg is None)


def calibration_pass(
    reader,
    infos,
    config,
    frame_filter,
    max_sigma_deg: float | None,
    progress: bool = False,
    forked: bool = True,
    continue_log_scenes: bool = True,
) -> CalibrationPassResult:
    """:func:`estimate_calibration`, with ``forked`` in a forked process as the run's odometry
    is: kiss-icp may ``abort()`` the process it runs in, which then ends with a clear error
    instead of taking this one with it."""
    estimate = functools.partial(
        estimate_calibration,
        reader,
        infos,
        config,
        frame_filter,
        max_sigma_deg,
        progress,
        continue_log_scenes,
    )
    if not forked:
        return estimate()
    import multiprocessing as mp
    import queue as queue_mod

    from radarslam.io.atomic import interrupts_deferred

    ctx = mp.get_context("fork")
    results = ctx.Queue(maxsize=1)
    proc = ctx.Process(  # fork: the partial is not pickled
        target=_calibration_process,
        args=(estimate, results, os.getpid()),
        name="slam-calibration",
    )
    proc.daemon = True
    with interrupts_deferred():  # as in OdometryFeed.run_forked
        proc.start()
    finished = False
    try:
        while True:
            try:
                message = results.get(timeout=REAP_EVERY_S)
            except queue_mod.Empty:
                if not proc.is_alive():
                    raise DataError(
                        f"the calibration pass process ended without finishing (exit code "
                        f"{proc.exitcode}; scenes {infos[0].name}..)"
                    ) from None
                continue
            finished = True
            if isinstance(message, Failed):
                raise message.error
            return message
    finally:
        # Ctrl-C or an error here: the helper ignores SIGINT, stop it now
        end_helper(proc, stop_now=not finished)


def _calibration_process(estimate: Callable[[], CalibrationPassResult], results, parent) -> None:
    try:
        helper_process_setup(parent)
        # Every scene the pass reads, the run reads again in its own process and reports (empty
        # sweeps, broken prev/next chains): the reader's once-per-scene notes would come twice.
        logging.getLogger("radarslam.nuscenes").setLevel(logging.ERROR)
        results.put(estimate())
    except BaseException as exc:  # handed to the parent, which raises it
        put_error(results, exc, "calibration pass process")
    finally:
        results.close()
        results.join_thread()
