"""Radar statistics of a dataroot, computed the same way on any dataroot (real or synthetic).

``radarslam stats DATAROOT --reference REF`` runs this on both and prints the figures side by
side, so a synthetic world is judged against measured real sweeps rather than remembered figures.

What is measured (one reading pass per scene, :func:`read_scene`, then one pure function per
group of figures):

* Points are those the odometry reads: its point filter (``OdometryConfig().points``:
  invalid_state 0, ambig_state 3, every dyn_prop), unless a figure says "before filtering"
  (every point the reader returns: NaN points and absurd coordinates are already dropped).
* "Doppler-static" and "moving" come from the odometry's joint Doppler fit
  (:meth:`DopplerEstimator.fit_frame` with ``OdometryConfig().doppler``) on each frame of the
  reader's five-radar grouping: a point is static when it is an inlier of a valid fit. Points of
  a frame whose fit is invalid are neither (no source for re-detection, not counted as moving).
* Re-detection: each Doppler-static point of a sweep is moved into the sensor frame of the
  following sweeps of the same radar with the dataset's ground-truth ego poses and calibration;
  it is re-detected when a filtered point of that sweep lies within ``radius_m`` (in the sensor's
  xy plane). "next" counts points that have a next sweep, "within 3" points that have three.
* Doppler residual: each point's radial velocity minus what a static point there would read
  under its frame's fit (:meth:`DopplerEstimator.radial_residuals`), over frames with a valid
  fit: its spread is the radar's Doppler noise.
* Doppler drive: per scene, the fit's yaw rate and speed (the last valid fit held over invalid
  ones, 0 before the first) integrated over the frames (trapezoid rule) against the ground-truth
  heading change and path length at the same frames.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from radarslam.nuscenes.filters import RadarPointFilter
from radarslam.types import RADAR_CHANNELS, RadarSweep

REDETECT_RADIUS_M = 1.0
REDETECT_LOOKAHEAD = 3


# --- what one reading pass keeps ---------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class SweepRecord:
    """One radar sweep after the point filter, with the Doppler fit's verdict per point."""

    channel: str
    timestamp_us: int
    raw_count: int  # points before filtering
    xyz: np.ndarray  # (N, 3) filtered points in the sensor frame
    rcs: np.ndarray  # (N,) dBsm
    static: np.ndarray  # (N,) bool: inlier of a valid joint Doppler fit
    fitted: bool  # the sweep's frame had a valid fit (False also for a sweep in no frame)
    world_from_sensor: np.ndarray  # 4x4, ground truth
    # (N,) measured radial velocity minus the frame fit's prediction for a static point there
    # (DopplerEstimator.radial_residuals); NaN without a valid fit. None: not recorded.
    doppler_residual_mps: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.xyz)


@dataclass(frozen=True, eq=False)
class FrameRecord:
    """One frame's joint Doppler fit and its ground-truth pose."""

    timestamp_us: int
    valid: bool
    twist: np.ndarray  # (3,) vx, vy (m/s, ego frame), yaw rate (rad/s)
    world_from_ego: np.ndarray  # 4x4 at timestamp_us


@dataclass(frozen=True, eq=False)
class SceneRecord:
    name: str
    sweeps: dict[str, list[SweepRecord]]  # channel -> its sweeps in time order
    frames: list[FrameRecord]


def odometry_inputs():
    """(point filter, Doppler estimator) of the odometry's default configuration."""
    from radarslam.odometry.config import OdometryConfig
    from radarslam.odometry.doppler import DopplerEstimator

    cfg = OdometryConfig()
    pc = cfg.points
    filt = RadarPointFilter(pc.invalid_states, pc.dynprop_states, pc.ambig_states)
    return filt, DopplerEstimator(cfg.doppler)


def filter_text(point_filter: RadarPointFilter) -> str:
    """``invalid_state 0, ambig_state 3``: the states a filter keeps, "no filter" when none."""
    parts = []
    for name, states in (
        ("invalid_state", point_filter.invalid_states),
        ("dyn_prop", point_filter.dynprop_states),
        ("ambig_state", point_filter.ambig_states),
    ):
        if states is not None:
            parts.append(f"{name} {','.join(str(v) for v in sorted(states))}")
    return ", ".join(parts) or "no filter"


def _record(
    sweep: RadarSweep,
    raw_count: int,
    static: np.ndarray,
    fitted: bool,
    residual: np.ndarray | None = None,
) -> SweepRecord:
    p = sweep.points
    xyz = np.column_stack([p["x"], p["y"], p["z"]]).astype(np.float64)
    return SweepRecord(
        channel=sweep.channel,
        timestamp_us=int(sweep.timestamp_us),
        raw_count=raw_count,
        xyz=xyz,
        rcs=p["rcs"].astype(np.float64),
        static=np.asarray(static, dtype=bool).copy(),
        fitted=fitted,
        world_from_sensor=sweep.world_from_sensor,
        doppler_residual_mps=np.full(len(sweep), np.nan) if residual is None else residual,
    )


def read_scene(
    reader,
    scene,
    point_filter: RadarPointFilter,
    estimator,
    max_frames: int | None = None,
    on_frame=None,
) -> SceneRecord:
    """Read one scene of a :class:`NuScenesRadar` frame by frame and fit each frame.

    ``max_frames`` keeps the first frames only (and each radar's sweeps up to its last one read);
    ``on_frame()`` is called after each frame (a progress bar)."""
    info = reader.scene(scene)
    everything = RadarPointFilter.none()
    by_token: dict[str, SweepRecord] = {}
    frames: list[FrameRecord] = []
    for k, frame in enumerate(reader.iter_frames(info, filters=everything)):
        if max_frames is not None and k >= max_frames:
            break
        raw = {ch: len(sw) for ch, sw in frame.sweeps.items()}
        kept = [sw.with_points(point_filter.apply(sw.points)) for sw in frame.sweeps.values()]
        fit = estimator.fit_frame(kept)
        for sw in kept:
            static = fit.static_masks.get(sw.channel) if fit.valid else None
            if static is None:
                static = np.zeros(len(sw), dtype=bool)
            residual = estimator.radial_residuals(sw, fit)
            by_token[sw.token] = _record(sw, raw[sw.channel], static, fit.valid, residual)
        frames.append(
            FrameRecord(
                timestamp_us=int(frame.timestamp_us),
                valid=bool(fit.valid),
                twist=np.asarray(fit.twist, dtype=np.float64),
                world_from_ego=np.asarray(frame.world_from_ego, dtype=np.float64),
            )
        )
        if on_frame is not None:
            on_frame()
    sweeps: dict[str, list[SweepRecord]] = {}
    for ch in RADAR_CHANNELS:
        tokens = reader.sweep_tokens(info, ch)
        read = [i for i, t in enumerate(tokens) if t in by_token]
        # A sweep no frame took (no anchor within the sync tolerance) still belongs to its
        # radar's chain: a re-detection target, never a source (no fit judged its points).
        last = (read[-1] if read else -1) if max_frames is not None else len(tokens) - 1
        chain = []
        for tok in tokens[: last + 1]:
            rec = by_token.get(tok)
            if rec is None:
                sw = reader.load_sweep(tok, filters=everything)
                kept = sw.with_points(point_filter.apply(sw.points))
                rec = _record(kept, len(sw), np.zeros(len(kept), dtype=bool), False)
            chain.append(rec)
        sweeps[ch] = chain
    return SceneRecord(name=info.name, sweeps=sweeps, frames=frames)


# --- statistics ----------------------------------------------------------------------------------


def _nan_to_none(x):
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: _nan_to_none(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_nan_to_none(v) for v in x]
    return x


def _percentiles(values: np.ndarray, qs: Iterable[int] = (10, 50, 90)) -> dict[str, float]:
    if len(values) == 0:
        return {f"p{q}": float("nan") for q in qs}
    return {f"p{q}": float(np.percentile(values, q)) for q in qs}


def _all_sweeps(scenes: Sequence[SceneRecord], channel: str | None = None) -> list[SweepRecord]:
    chans = RADAR_CHANNELS if channel is None else (channel,)
    return [s for sc in scenes for ch in chans for s in sc.sweeps.get(ch, [])]


@dataclass
class PointCounts:
    """Points per sweep (after the filter unless ``raw``), over every radar's sweeps."""

    num_sweeps: int
    raw_mean: float
    mean: float
    p10: float
    p50: float
    p90: float
    empty_fraction: float  # sweeps with no point left after the filter
    per_radar_mean: dict[str, float]


def point_counts(scenes: Sequence[SceneRecord]) -> PointCounts:
    sweeps = _all_sweeps(scenes)
    n = np.array([len(s) for s in sweeps], dtype=np.float64)
    raw = np.array([s.raw_count for s in sweeps], dtype=np.float64)
    pct = _percentiles(n)
    per_radar = {}
    for ch in RADAR_CHANNELS:
        c = [len(s) for s in _all_sweeps(scenes, ch)]
        per_radar[ch] = float(np.mean(c)) if c else float("nan")
    return PointCounts(
        num_sweeps=len(sweeps),
        raw_mean=float(raw.mean()) if len(raw) else float("nan"),
        mean=float(n.mean()) if len(n) else float("nan"),
        p10=pct["p10"],
        p50=pct["p50"],
        p90=pct["p90"],
        empty_fraction=float((n == 0).mean()) if len(n) else float("nan"),
        per_radar_mean=per_radar,
    )


@dataclass
class Redetection:
    """Fraction of Doppler-static points re-detected by the same radar within ``radius_m``."""

    radius_m: float
    lookahead: int
    next: float  # in the next sweep
    within: float  # in any of the next ``lookahead`` sweeps
    sources_next: int  # static points that had a next sweep
    sources_within: int  # static points that had ``lookahead`` later sweeps
    per_radar_next: dict[str, float]
    per_radar_within: dict[str, float]


def _hits(src: SweepRecord, dst: SweepRecord, radius_m: float) -> np.ndarray:
    """(M,) whether each static point of ``src``, moved into ``dst``'s sensor frame, has a point
    of ``dst`` within ``radius_m`` in the xy plane."""
    pts = src.xyz[src.static]
    if len(pts) == 0 or len(dst) == 0:
        return np.zeros(len(pts), dtype=bool)
    t = np.linalg.solve(dst.world_from_sensor, src.world_from_sensor)
    moved = pts @ t[:3, :3].T + t[:3, 3]
    d2 = ((moved[:, None, :2] - dst.xyz[None, :, :2]) ** 2).sum(-1)
    return d2.min(axis=1) <= radius_m * radius_m


def _redetect_chain(chain: Sequence[SweepRecord], radius_m: float, lookahead: int):
    """(hits next, sources next, hits within, sources within) of one radar's sweeps."""
    h1 = n1 = hk = nk = 0
    for i, src in enumerate(chain):
        m = int(src.static.sum())
        if m == 0 or i + 1 >= len(chain):
            continue
        hit = np.zeros(m, dtype=bool)
        for j in range(1, lookahead + 1):
            if i + j >= len(chain):
                break
            h = _hits(src, chain[i + j], radius_m)
            if j == 1:
                h1, n1 = h1 + int(h.sum()), n1 + m
            hit |= h
        if i + lookahead < len(chain):
            hk, nk = hk + int(hit.sum()), nk + m
    return h1, n1, hk, nk


def redetection(
    scenes: Sequence[SceneRecord],
    radius_m: float = REDETECT_RADIUS_M,
    lookahead: int = REDETECT_LOOKAHEAD,
) -> Redetection:
    per: dict[str, tuple[int, int, int, int]] = {}
    for ch in RADAR_CHANNELS:
        tot = np.zeros(4, dtype=np.int64)
        for sc in scenes:
            tot += np.array(_redetect_chain(sc.sweeps.get(ch, []), radius_m, lookahead))
        h1, n1, hk, nk = (int(x) for x in tot)
        per[ch] = (h1, n1, hk, nk)

    def frac(h: int, n: int) -> float:
        return h / n if n else float("nan")

    h1, n1, hk, nk = (sum(v[i] for v in per.values()) for i in range(4))
    return Redetection(
        radius_m=radius_m,
        lookahead=lookahead,
        next=frac(h1, n1),
        within=frac(hk, nk),
        sources_next=n1,
        sources_within=nk,
        per_radar_next={ch: frac(v[0], v[1]) for ch, v in per.items()},
        per_radar_within={ch: frac(v[2], v[3]) for ch, v in per.items()},
    )


@dataclass
class SceneDrive:
    duration_s: float
    heading_error_deg: float  # integrated fit yaw rate minus ground-truth heading change
    gt_heading_change_deg: float
    fit_path_m: float
    gt_path_m: float


@dataclass
class DopplerDrive:
    """The joint Doppler fit integrated over each scene against the ground truth."""

    num_scenes: int  # scenes with at least two frames
    valid_fraction: float  # frames whose fit was valid
    heading_error_worst_dps: float  # max over scenes of |heading error| / duration
    heading_error_median_dps: float
    speed_scale: float  # fit path length / ground-truth path length, all scenes pooled
    per_scene: dict[str, SceneDrive] = field(default_factory=dict)


def _yaw(world_from_ego: np.ndarray) -> float:
    return math.atan2(world_from_ego[1, 0], world_from_ego[0, 0])


def scene_drive(frames: Sequence[FrameRecord]) -> SceneDrive | None:
    """The fit integrated over one scene's frames; None with fewer than two frames."""
    if len(frames) < 2:
        return None
    t = np.array([f.timestamp_us for f in frames], dtype=np.float64) * 1e-6
    twist = np.zeros((len(frames), 3))
    held = np.zeros(3)
    for k, f in enumerate(frames):
        if f.valid and np.all(np.isfinite(f.twist)):
            held = f.twist
        twist[k] = held
    dt = np.diff(t)
    yaw_rate = twist[:, 2]
    speed = np.hypot(twist[:, 0], twist[:, 1])
    fit_yaw = float(np.sum(0.5 * (yaw_rate[1:] + yaw_rate[:-1]) * dt))
    fit_path = float(np.sum(0.5 * (speed[1:] + speed[:-1]) * dt))
    yaws = np.array([_yaw(f.world_from_ego) for f in frames])
    dyaw = (np.diff(yaws) + np.pi) % (2 * np.pi) - np.pi  # summed steps: turns beyond 180 deg
    xy = np.array([f.world_from_ego[:2, 3] for f in frames])
    gt_path = float(np.linalg.norm(np.diff(xy, axis=0), axis=1).sum())
    return SceneDrive(
        duration_s=float(t[-1] - t[0]),
        heading_error_deg=math.degrees(fit_yaw - float(dyaw.sum())),
        gt_heading_change_deg=math.degrees(float(dyaw.sum())),
        fit_path_m=fit_path,
        gt_path_m=gt_path,
    )


def doppler_drive(scenes: Sequence[SceneRecord]) -> DopplerDrive:
    per = {}
    for sc in scenes:
        d = scene_drive(sc.frames)
        if d is not None:
            per[sc.name] = d
    rates = [abs(d.heading_error_deg) / d.duration_s for d in per.values() if d.duration_s > 0]
    fit_path = sum(d.fit_path_m for d in per.values())
    gt_path = sum(d.gt_path_m for d in per.values())
    frames = [f for sc in scenes for f in sc.frames]
    return DopplerDrive(
        num_scenes=len(per),
        valid_fraction=float(np.mean([f.valid for f in frames])) if frames else float("nan"),
        heading_error_worst_dps=float(max(rates)) if rates else float("nan"),
        heading_error_median_dps=float(np.median(rates)) if rates else float("nan"),
        speed_scale=fit_path / gt_path if gt_path > 0 else float("nan"),
        per_scene=per,
    )


@dataclass
class PointDistribution:
    """Range and RCS of the filtered points, and the share the Doppler fit calls moving; over
    every radar, and per radar (the side-looking corner units see other things)."""

    num_points: int
    range_m: dict[str, float]  # p10, p50, p90
    rcs_dbsm: dict[str, float]  # p10, p50, p90
    moving_fraction: float  # of the points of sweeps with a valid fit: not Doppler-static
    # |radial velocity - the frame fit's prediction for a static point| of the points of
    # sweeps with a valid fit, p50 and p75 (m/s): the radar's Doppler noise, static points
    # being most of them
    doppler_residual_mps: dict[str, float] = field(default_factory=dict)
    per_radar_range_p50_m: dict[str, float] = field(default_factory=dict)
    per_radar_range_p90_m: dict[str, float] = field(default_factory=dict)
    per_radar_rcs_p50_dbsm: dict[str, float] = field(default_factory=dict)
    per_radar_moving_fraction: dict[str, float] = field(default_factory=dict)


def _distribution(sweeps: Sequence[SweepRecord]) -> tuple[np.ndarray, np.ndarray, float]:
    """(ranges, RCS levels, moving fraction) of the points of ``sweeps``."""
    sweeps = [s for s in sweeps if len(s)]
    if not sweeps:
        return np.zeros(0), np.zeros(0), math.nan
    rng = np.concatenate([np.hypot(s.xyz[:, 0], s.xyz[:, 1]) for s in sweeps])
    rcs = np.concatenate([s.rcs for s in sweeps])
    fitted = [s for s in sweeps if s.fitted]
    n_fit = sum(len(s) for s in fitted)
    moving = sum(len(s) - int(s.static.sum()) for s in fitted)
    return rng, rcs, (moving / n_fit if n_fit else math.nan)


def _residuals(sweeps: Sequence[SweepRecord]) -> np.ndarray:
    parts = [
        np.abs(s.doppler_residual_mps)
        for s in sweeps
        if s.fitted and len(s) and s.doppler_residual_mps is not None
    ]
    res = np.concatenate(parts) if parts else np.zeros(0)
    return res[np.isfinite(res)]


def point_distribution(scenes: Sequence[SceneRecord]) -> PointDistribution:
    rng, rcs, moving = _distribution(_all_sweeps(scenes))
    per = {ch: _distribution(_all_sweeps(scenes, ch)) for ch in RADAR_CHANNELS}
    return PointDistribution(
        num_points=len(rng),
        range_m=_percentiles(rng),
        rcs_dbsm=_percentiles(rcs),
        moving_fraction=moving,
        doppler_residual_mps=_percentiles(_residuals(_all_sweeps(scenes)), (50, 75)),
        per_radar_range_p50_m={ch: _percentiles(d[0], (50,))["p50"] for ch, d in per.items()},
        per_radar_range_p90_m={ch: _percentiles(d[0], (90,))["p90"] for ch, d in per.items()},
        per_radar_rcs_p50_dbsm={ch: _percentiles(d[1], (50,))["p50"] for ch, d in per.items()},
        per_radar_moving_fraction={ch: d[2] for ch, d in per.items()},
    )


@dataclass
class DatasetStats:
    dataroot: str
    version: str
    num_scenes: int
    num_frames: int
    counts: PointCounts
    redetection: Redetection
    doppler: DopplerDrive
    points: PointDistribution

    def to_dict(self) -> dict:
        """Plain JSON types; NaN (a figure with nothing to measure) becomes null."""
        return _nan_to_none(asdict(self))


def statistics_of(
    scenes: Sequence[SceneRecord], dataroot: str = "", version: str = ""
) -> DatasetStats:
    """Every figure of already read scenes."""
    return DatasetStats(
        dataroot=dataroot,
        version=version,
        num_scenes=len(scenes),
        num_frames=sum(len(sc.frames) for sc in scenes),
        counts=point_counts(scenes),
        redetection=redetection(scenes),
        doppler=doppler_drive(scenes),
        points=point_distribution(scenes),
    )


def dataset_statistics(
    reader,
    scenes: Sequence[str] | None = None,
    max_frames_per_scene: int | None = None,
    progress: bool = True,
    desc: str = "radar statistics",
) -> DatasetStats:
    """Statistics of the radar sweeps of ``scenes`` (default: all) of a :class:`NuScenesRadar`.

    ``max_frames_per_scene`` keeps the first frames of each scene (one sweep per radar each)."""
    from tqdm import tqdm

    infos = [reader.scene(s) for s in scenes] if scenes else reader.scenes()
    point_filter, estimator = odometry_inputs()
    total = 0
    for info in infos:
        n = len(reader.frame_groups(info))
        total += n if max_frames_per_scene is None else min(n, max_frames_per_scene)
    # delay: quick runs (a few scenes) print no bar at all
    with tqdm(
        total=total, desc=desc, unit="frame", delay=2.0, disable=None if progress else True
    ) as bar:
        records = [
            read_scene(
                reader,
                info,
                point_filter,
                estimator,
                max_frames=max_frames_per_scene,
                on_frame=lambda: bar.update(1),
            )
            for info in infos
        ]
    return statistics_of(records, str(reader.dataroot), reader.version)
