"""A vehicle's radar rig and its Doppler calibration: what the odometry's filter estimated
(:class:`DopplerCalibration`), how the sweeps take a mounting-yaw correction
(:func:`mounting_rotations`, :func:`with_mounting`), and how one vehicle's rig is told from
another's by its nominal extrinsics (:func:`nominal_extrinsics`, :func:`find_rig`): mounting
errors belong to a car, and one run may drive scenes of several cars.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from radarslam.odometry.lie import exp_se2
from radarslam.types import RADAR_CHANNELS, RadarFrame


@dataclass(frozen=True)
class DopplerCalibration:
    """The Doppler calibration the fusion filter has estimated so far: each state's value and
    sigma. ``yaw_bias_model`` says which yaw states exist: "per_metre" (rad/m), "rate" (rad/s),
    "mounting" (one mounting-yaw error per radar, rad) or "none"."""

    yaw_bias_model: str
    yaw_states: tuple[float, ...]
    yaw_sigmas: tuple[float, ...]
    speed_scale_error: float  # true speed = Doppler speed x (1 + this)
    speed_scale_sigma: float
    #: The radars' Doppler scale the fit undid (``doppler.speed_scale_error``, configured): they
    #: read (1 + this) x the true radial velocity; ``speed_scale_error`` is what is left.
    radar_speed_scale_error: float = 0.0
    #: The radar rig this calibration belongs to (:func:`rig_id`) and the scenes driven with it.
    rig: str = ""
    scenes: tuple[str, ...] = ()

    def as_dict(self) -> dict:
        out: dict = {
            "yaw_bias_model": self.yaw_bias_model,
            "radar_speed_scale_error": self.radar_speed_scale_error,
        }
        if self.rig:
            out["rig"] = self.rig
            out["scenes"] = list(self.scenes)
        deg = [math.degrees(v) for v in self.yaw_states]
        deg_sig = [math.degrees(v) for v in self.yaw_sigmas]
        if self.yaw_bias_model == "mounting":
            out["mounting_yaw_error_deg"] = dict(zip(RADAR_CHANNELS, deg, strict=True))
            out["mounting_yaw_sigma_deg"] = dict(zip(RADAR_CHANNELS, deg_sig, strict=True))
        elif self.yaw_bias_model == "per_metre":
            out["yaw_bias_deg_per_100m"] = 100.0 * deg[0]
            out["yaw_bias_sigma_deg_per_100m"] = 100.0 * deg_sig[0]
        elif self.yaw_bias_model == "rate":
            out["yaw_bias_deg_per_s"] = deg[0]
            out["yaw_bias_sigma_deg_per_s"] = deg_sig[0]
        if self.yaw_bias_model != "none":
            out["speed_scale_error"] = self.speed_scale_error
            out["speed_scale_sigma"] = self.speed_scale_sigma
        return out


def mounting_rotations(mounting_yaw_deg: dict[str, float]) -> dict[str, np.ndarray]:
    """Per channel, the 4x4 sensor rotation by its mounting-yaw error (deg)."""
    return {
        ch: exp_se2(np.array([0.0, 0.0, math.radians(deg)])) for ch, deg in mounting_yaw_deg.items()
    }


def nominal_extrinsics(ego_from_sensor: Mapping[str, np.ndarray]) -> dict[str, bytes]:
    """Per channel, the nominal ``ego_from_sensor`` rounded to 0.1 mm and 1e-4 of a rotation
    entry: what tells one vehicle's radar rig from another's."""
    return {
        ch: np.round(np.asarray(m, dtype=np.float64), 4).tobytes()
        for ch, m in ego_from_sensor.items()
    }


def rig_extrinsics(frame: RadarFrame) -> dict[str, bytes]:
    """:func:`nominal_extrinsics` of ``frame``'s sweeps."""
    return nominal_extrinsics({ch: sw.ego_from_sensor for ch, sw in frame.sweeps.items()})


def same_rig(a: dict[str, bytes], b: dict[str, bytes]) -> bool:
    """Whether two sets of :func:`nominal_extrinsics` can be one rig: they share a channel and
    no shared channel differs (a frame may lack any radar's sweep)."""
    shared = a.keys() & b.keys()
    return bool(shared) and all(a[ch] == b[ch] for ch in shared)


def find_rig(
    known: Sequence[dict[str, bytes]], extrinsics: dict[str, bytes], current: int | None
) -> int | None:
    """Index in ``known`` of the rig ``extrinsics`` belong to, or None for a new rig: the
    ``current`` one while nothing contradicts it (no shared channel is no evidence), else the
    first that shares a channel and agrees on all shared."""
    if current is not None:
        rig = known[current]
        if same_rig(rig, extrinsics) or not rig.keys() & extrinsics.keys():
            return current
    return next((i for i, rig in enumerate(known) if same_rig(rig, extrinsics)), None)


def merge_extrinsics(into: dict[str, bytes], extrinsics: dict[str, bytes]) -> None:
    """Add the channels ``into`` has not shown yet."""
    for ch, value in extrinsics.items():
        into.setdefault(ch, value)


def rig_id(extrinsics: dict[str, bytes]) -> str:
    """A short stable name of a rig's nominal extrinsics (:func:`rig_extrinsics`)."""
    h = hashlib.sha1()
    for ch in sorted(extrinsics):
        h.update(ch.encode())
        h.update(extrinsics[ch])
    return h.hexdigest()[:8]


def count_rigs(reader, infos) -> int:
    """How many radar rigs the scenes come from, by their radars' nominal extrinsics
    (``reader.scene_extrinsics``, no file read) and the rule the odometry uses to tell rigs
    apart (:func:`~radarslam.odometry.calibration.find_rig`)."""
    rigs: list[dict[str, bytes]] = []
    current = None
    for info in infos:
        ext = nominal_extrinsics(reader.scene_extrinsics(info))
        if not ext:
            continue
        current = find_rig(rigs, ext, current)
        if current is None:
            rigs.append(ext)
            current = len(rigs) - 1
        else:
            merge_extrinsics(rigs[current], ext)
    return len(rigs)


@dataclass
class Rig:
    """One radar rig (a vehicle's nominal extrinsics) and the calibration estimated for it while
    another rig's scenes run: mounting errors belong to a car, and nuScenes drives of several
    cars can share one run."""

    extrinsics: dict[str, bytes]
    calib: np.ndarray
    calib_cov: np.ndarray
    folded: np.ndarray
    scenes: list[str] = field(default_factory=list)

    @property
    def name(self) -> str:
        return rig_id(self.extrinsics)

    def learn(self, frame: RadarFrame) -> None:
        """Add the nominal extrinsics of channels this rig has not shown yet."""
        if frame.sweeps.keys() - self.extrinsics.keys():
            merge_extrinsics(self.extrinsics, rig_extrinsics(frame))


def with_mounting(frame: RadarFrame, rotations: dict[str, np.ndarray]) -> RadarFrame:
    """``frame`` with each sweep's ``ego_from_sensor`` turned by its channel's rotation
    (:func:`mounting_rotations`)."""
    if not rotations:
        return frame
    sweeps = {
        ch: dataclasses.replace(sw, ego_from_sensor=sw.ego_from_sensor @ rotations[ch])
        if ch in rotations
        else sw
        for ch, sw in frame.sweeps.items()
    }
    return dataclasses.replace(frame, sweeps=sweeps)
