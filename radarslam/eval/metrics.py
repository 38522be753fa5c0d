"""Trajectory error metrics: the pure-math core of ``radarslam eval`` (evo-like layering).

Layers: plane geometry helpers -> one function per metric returning a frozen result dataclass
(:func:`ate`, :func:`ate_clock_offsets`, :func:`rpe`, :func:`drift`, :func:`turn_scale`) ->
the results-folder evaluator (``evaluate.py``) -> CLI.

Everything is evaluated **in the ground plane**: poses are projected to (x, y, yaw) before any
alignment or error, because the radar estimate is planar while nuScenes ground truth carries a
little z / roll / pitch that the radars cannot observe. On planar trajectories the numbers equal
evo's ``ape``/``rpe`` with ``align=True, correct_scale=False`` (checked in the tests), and the
``"sim2"`` alignment evo's ``correct_scale=True``.

Inputs are ``(N, 4, 4)`` ``world_from_ego`` poses or ``(N, 3)`` (x, y, yaw) arrays, estimate and
reference already associated index by index.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from radarslam.errors import DataError
from radarslam.geometry import repair_rotations, rot2, yaw_of, yaws_of
from radarslam.timestamps import check_timestamps_us

#: Rotation-block tolerance of (N, 4, 4) inputs: the trajectory files' (what read_kitti accepts).
POSE_TOLERANCE = 1e-3

AlignMode = Literal["se2", "sim2", "none", "first"]
DeltaUnit = Literal["s", "m", "frames"]


# --- plane geometry ----------------------------------------------------------------------------


def to_xy_yaw(poses, what: str = "poses") -> np.ndarray:
    """(N, 3) (x, y, yaw) from (N, 4, 4) poses or an (N, 3) array (returned as float64 copy).

    4x4 poses must be rigid (rotation block orthonormal with det +1, bottom row 0 0 0 1, within
    :data:`POSE_TOLERANCE`): the yaw of a scaled or skewed block means nothing. Rotation blocks
    off by up to :data:`~radarslam.geometry.REPAIR_TOLERANCE` (poses printed with few digits,
    as evo reads them) are re-orthonormalised, with one :class:`UserWarning`."""
    try:
        arr = np.asarray(poses, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f"{what}: poses must be numeric (N, 4, 4) or (N, 3) arrays") from None
    if arr.ndim == 3 and arr.shape[1:] == (4, 4):
        try:
            fixed = repair_rotations(arr, POSE_TOLERANCE)
        except ValueError as exc:
            raise DataError(f"{what}: pose {exc.args[0]} {exc.args[1]}") from None
        if fixed.count:
            # the same text for the same poses: Python shows it once however many metrics read them
            warnings.warn(
                f"{what}: {fixed.count} of {len(arr)} pose(s) have a rotation block off by up to "
                f"{fixed.worst:.3g} (max |R R^T - I|); re-orthonormalised",
                UserWarning,
                stacklevel=2,
            )
        arr = fixed.poses
        out = np.column_stack([arr[:, 0, 3], arr[:, 1, 3], yaws_of(arr)])
    elif arr.ndim == 2 and arr.shape[1] == 3:
        out = arr.copy()
    else:
        raise DataError(f"{what}: expected (N, 4, 4) poses or (N, 3) x/y/yaw, got {arr.shape}")
    if not np.all(np.isfinite(out)):
        raise DataError(f"{what}: non-finite pose values")
    return out


def _check_pair(est, ref) -> tuple[np.ndarray, np.ndarray]:
    e = to_xy_yaw(est, "estimate")
    r = to_xy_yaw(ref, "reference")
    if len(e) != len(r):
        raise DataError(f"estimate has {len(e)} poses but reference has {len(r)}")
    if len(e) == 0:
        raise DataError("no poses to evaluate")
    return e, r


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def se2_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a⁻¹ ⊕ b (the pose of b in a's frame) for (..., 3) arrays."""
    c, s = np.cos(a[..., 2]), np.sin(a[..., 2])
    dx, dy = b[..., 0] - a[..., 0], b[..., 1] - a[..., 1]
    return np.stack([c * dx + s * dy, -s * dx + c * dy, _wrap(b[..., 2] - a[..., 2])], axis=-1)


@dataclass(frozen=True)
class Alignment2D:
    """``ref_from_est`` planar transform: p_ref = scale R p_est + t (rigid where scale is 1)."""

    rotation: np.ndarray  # (2, 2)
    translation: np.ndarray  # (2,)
    # reference length / estimated length: above 1, the estimate is too short
    scale: float = 1.0

    @property
    def yaw_rad(self) -> float:
        return yaw_of(self.rotation)

    @property
    def matrix(self) -> np.ndarray:
        """4x4 ``ref_from_est`` (a similarity where :attr:`scale` is not 1)."""
        out = np.eye(4)
        out[:2, :2] = self.scale * self.rotation
        out[:2, 3] = self.translation
        return out

    def apply(self, xy_yaw: np.ndarray) -> np.ndarray:
        out = np.empty_like(xy_yaw)
        out[:, :2] = self.scale * xy_yaw[:, :2] @ self.rotation.T + self.translation
        out[:, 2] = _wrap(xy_yaw[:, 2] + self.yaw_rad)
        return out


IDENTITY_ALIGNMENT = Alignment2D(np.eye(2), np.zeros(2))


def align_se2(est_xy, ref_xy) -> Alignment2D:
    """Least-squares rigid alignment in the plane (Umeyama without scale): ``ref ≈ R est + t``.

    Accepts (N, 2) positions, (N, 3) x/y/yaw or (N, 4, 4) poses (only positions are used).
    """
    return _umeyama(est_xy, ref_xy, with_scale=False)


def align_sim2(est_xy, ref_xy) -> Alignment2D:
    """Least-squares similarity alignment in the plane (Umeyama): ``ref ≈ s R est + t``.

    ``s`` (:attr:`Alignment2D.scale`) is the reference's length over the estimate's: a speed
    scale error of the estimate shows there. A path that winds where the reference is straight
    also comes out short, so on a long drive it mixes shape with speed. Positions that do not
    spread (every one the same) leave the scale at 1."""
    return _umeyama(est_xy, ref_xy, with_scale=True)


def _umeyama(est_xy, ref_xy, with_scale: bool) -> Alignment2D:
    e = _positions(est_xy, "estimate")
    r = _positions(ref_xy, "reference")
    if len(e) != len(r):
        raise DataError(f"alignment: estimate has {len(e)} positions, reference {len(r)}")
    if len(e) == 0:
        raise DataError("alignment: no positions")
    mean_e, mean_r = e.mean(axis=0), r.mean(axis=0)
    cov = (r - mean_r).T @ (e - mean_e) / len(e)
    u, d, vt = np.linalg.svd(cov)
    if np.count_nonzero(d > 1e-12 * max(1.0, d[0])) < 1:
        # every position identical: only the translation is observable
        return Alignment2D(np.eye(2), mean_r - mean_e)
    s = np.eye(2)
    if np.linalg.det(u) * np.linalg.det(vt) < 0:
        s[1, 1] = -1.0  # proper rotation, never a reflection
    rot = u @ s @ vt
    scale = 1.0
    if with_scale:
        spread = float(np.mean(np.sum((e - mean_e) ** 2, axis=1)))
        scale = float(np.sum(d * np.diag(s)) / spread)
    return Alignment2D(rot, mean_r - scale * rot @ mean_e, scale)


def _positions(a, what: str) -> np.ndarray:
    arr = np.asarray(a, dtype=np.float64)
    if arr.ndim == 2 and arr.shape[1] == 2:
        pos = arr
    else:
        pos = to_xy_yaw(arr, what)[:, :2]
    if not np.all(np.isfinite(pos)):
        raise DataError(f"{what}: non-finite positions")
    return pos


def align_first(est_xy_yaw: np.ndarray, ref_xy_yaw: np.ndarray) -> Alignment2D:
    """The planar transform that puts the first estimated pose exactly on the first reference."""
    e0, r0 = est_xy_yaw[0], ref_xy_yaw[0]
    dyaw = r0[2] - e0[2]
    rot = rot2(float(dyaw))
    return Alignment2D(rot, r0[:2] - rot @ e0[:2])


# --- statistics --------------------------------------------------------------------------------


@dataclass(frozen=True)
class ErrorStats:
    rmse: float
    mean: float
    median: float
    std: float
    min: float
    max: float
    count: int

    @staticmethod
    def of(errors: np.ndarray) -> ErrorStats:
        e = np.asarray(errors, dtype=np.float64)
        if e.size == 0:
            nan = float("nan")
            return ErrorStats(nan, nan, nan, nan, nan, nan, 0)
        return ErrorStats(
            rmse=float(np.sqrt(np.mean(e * e))),
            mean=float(np.mean(e)),
            median=float(np.median(e)),
            std=float(np.std(e)),
            min=float(np.min(e)),
            max=float(np.max(e)),
            count=int(e.size),
        )


# --- absolute trajectory error -----------------------------------------------------------------


@dataclass(frozen=True)
class AteResult:
    """Absolute trajectory error (planar position error after alignment)."""

    rmse_m: float
    mean_m: float
    median_m: float
    max_m: float
    std_m: float
    yaw_rmse_deg: float
    errors_m: np.ndarray = field(repr=False)  # (N,) per-pose position error
    yaw_errors_deg: np.ndarray = field(repr=False)  # (N,) signed heading error
    alignment: Alignment2D = field(repr=False, default=IDENTITY_ALIGNMENT)
    align: str = "se2"
    # (N,) the position error in each reference pose's own frame: along its heading (+ ahead)
    # and across it (+ to its left). A clock offset or a speed-scale error shows along the
    # track, a heading error across it.
    along_errors_m: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))
    cross_errors_m: np.ndarray = field(repr=False, default_factory=lambda: np.zeros(0))

    @property
    def count(self) -> int:
        return int(self.errors_m.size)

    @property
    def along_rmse_m(self) -> float:
        """RMS of the error along the reference's heading (its share of :attr:`rmse_m`)."""
        return _rms(self.along_errors_m)

    @property
    def cross_rmse_m(self) -> float:
        """RMS of the error across the reference's heading."""
        return _rms(self.cross_errors_m)


def _rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(a * a))) if a.size else float("nan")


def ate(est_poses, ref_poses, align: AlignMode = "se2") -> AteResult:
    """Absolute trajectory error in the ground plane.

    align: ``"se2"`` least-squares rigid alignment of all positions (evo ``align=True``),
    ``"sim2"`` the same with a scale (evo ``correct_scale=True``; the scale is
    ``result.alignment.scale``), ``"first"`` the first poses made to coincide (how an unaligned
    odometry run is judged), or ``"none"`` (the estimate is already in the reference frame, e.g.
    SLAM anchored on the prior).
    """
    e, r = _check_pair(est_poses, ref_poses)
    if align == "se2":
        al = align_se2(e[:, :2], r[:, :2])
    elif align == "sim2":
        al = align_sim2(e[:, :2], r[:, :2])
    elif align == "first":
        al = align_first(e, r)
    elif align == "none":
        al = IDENTITY_ALIGNMENT
    else:
        raise DataError(f"ATE: unknown alignment {align!r} (expected se2, sim2, first or none)")
    aligned = al.apply(e)
    diff = aligned[:, :2] - r[:, :2]
    errors = np.linalg.norm(diff, axis=1)
    yaw_err = np.rad2deg(_wrap(aligned[:, 2] - r[:, 2]))
    c, s = np.cos(r[:, 2]), np.sin(r[:, 2])
    st = ErrorStats.of(errors)
    return AteResult(
        rmse_m=st.rmse,
        mean_m=st.mean,
        median_m=st.median,
        max_m=st.max,
        std_m=st.std,
        yaw_rmse_deg=float(np.sqrt(np.mean(yaw_err**2))),
        errors_m=errors,
        yaw_errors_deg=yaw_err,
        alignment=al,
        align=align,
        along_errors_m=c * diff[:, 0] + s * diff[:, 1],
        cross_errors_m=c * diff[:, 1] - s * diff[:, 0],
    )


@dataclass(frozen=True)
class ClockOffsetResult:
    """SE(2)-aligned ATE of an estimate against its reference read with its clock shifted.

    ``rmse_m[k]`` compares the estimate at its stamp t with the reference at t + ``offsets_s[k]``
    over the same ``count`` poses at every shift: a positive best offset means the estimate's
    stamps run early against the reference's clock. Radar alone cannot observe such an offset,
    so this tells how much of an ATE the two clocks make, not an error of the estimate."""

    offsets_s: np.ndarray  # (K,) the shifts tried, increasing, 0 among them
    rmse_m: np.ndarray  # (K,) ATE at each shift
    count: int  # poses compared at every shift

    @property
    def best_offset_s(self) -> float:
        return float(self.offsets_s[int(np.argmin(self.rmse_m))])

    @property
    def best_rmse_m(self) -> float:
        return float(np.min(self.rmse_m))

    @property
    def rmse_at_zero_m(self) -> float:
        """ATE over the compared poses with the clocks as stamped."""
        return float(self.rmse_m[int(np.argmin(np.abs(self.offsets_s)))])


def ate_clock_offsets(
    est_poses,
    est_timestamps_us,
    ref_poses,
    ref_timestamps_us,
    max_offset_s: float = 0.1,
    step_s: float = 0.005,
) -> ClockOffsetResult | None:
    """ATE (SE(2)-aligned) of the estimate against the reference interpolated (position and
    unwrapped yaw, linearly) at the estimate's stamps shifted by every multiple of ``step_s``
    within +-``max_offset_s``. Only poses whose every shifted time the reference covers are
    compared, so all shifts see the same poses; ``None`` when fewer than 2 remain.

    The reference's stamps must be strictly increasing; the estimate's may repeat."""
    if not (np.isfinite(max_offset_s) and np.isfinite(step_s)) or step_s <= 0 or max_offset_s < 0:
        raise DataError(
            f"clock offsets: need max_offset_s >= 0 and step_s > 0, got {max_offset_s!r} and "
            f"{step_s!r}"
        )
    e = to_xy_yaw(est_poses, "estimate")
    r = to_xy_yaw(ref_poses, "reference")
    te = check_timestamps_us(est_timestamps_us, len(e), "estimate", strictly_increasing=False)
    tr = check_timestamps_us(ref_timestamps_us, len(r), "reference")
    if len(r) < 2:
        return None
    k = int(np.floor(max_offset_s / step_s + 1e-9))
    offsets = np.arange(-k, k + 1) * step_s
    t = (te - tr[0]) * 1e-6  # seconds from the reference's first stamp, exact in float64
    tref = (tr - tr[0]) * 1e-6
    inside = (t + offsets[0] >= tref[0]) & (t + offsets[-1] <= tref[-1])
    if np.count_nonzero(inside) < 2:
        return None
    e, t = e[inside], t[inside]
    yaw = np.unwrap(r[:, 2])
    rmse = np.empty(len(offsets))
    for i, o in enumerate(offsets):
        shifted = np.column_stack(
            [np.interp(t + o, tref, r[:, 0]), np.interp(t + o, tref, r[:, 1]),
             np.interp(t + o, tref, yaw)]
        )  # fmt: skip
        rmse[i] = ate(e, shifted, align="se2").rmse_m
    return ClockOffsetResult(offsets, rmse, len(e))


# --- relative pose error -----------------------------------------------------------------------


def path_lengths_m(xy_yaw: np.ndarray) -> np.ndarray:
    """Cumulative travelled distance (N,) along the positions, starting at 0."""
    steps = np.linalg.norm(np.diff(xy_yaw[:, :2], axis=0), axis=1)
    return np.concatenate([[0.0], np.cumsum(steps)])


def pairs_for_delta(
    ref_xy_yaw: np.ndarray,
    timestamps_us: np.ndarray | None,
    delta: float,
    unit: DeltaUnit,
) -> np.ndarray:
    """(K, 2) index pairs (i, j): for every start i, the first j at least ``delta`` later.

    ``frames``: j = i + delta. ``s``: first j with t_j - t_i >= delta seconds (1 ms slack for
    sensor jitter). ``m``: first j whose travelled reference path from i is >= delta metres.
    Starts whose j would fall off the end are dropped.
    """
    n = len(ref_xy_yaw)
    if isinstance(delta, bool) or not isinstance(delta, (int, float, np.integer, np.floating)):
        raise DataError(f"RPE: delta must be a number, got {type(delta).__name__} {delta!r}")
    if not np.isfinite(delta) or delta <= 0:
        raise DataError(f"RPE: delta must be > 0, got {delta}")
    starts = np.arange(n)
    if unit == "frames":
        if delta != int(delta):
            raise DataError(f"RPE: delta in frames must be an integer, got {delta}")
        ends = starts + int(delta)
    elif unit == "s":
        if timestamps_us is None:
            raise DataError("RPE: delta in seconds needs timestamps_us")
        t = check_timestamps_us(timestamps_us, n, "RPE", strictly_increasing=False)
        if delta * 1e6 >= 2.0**62:
            ends = np.full(n, n)  # longer than any trajectory: no pair
        else:
            target = t + (round(delta * 1e6) - 1000)
            ends = np.searchsorted(t, target, side="left")
    elif unit == "m":
        d = path_lengths_m(ref_xy_yaw)
        ends = np.searchsorted(d, d + delta - 1e-9, side="left")
    else:
        raise DataError(f"RPE: unknown delta unit {unit!r} (expected s, m or frames)")
    keep = (ends < n) & (ends > starts)
    return np.column_stack([starts[keep], ends[keep]])


@dataclass(frozen=True)
class RpeResult:
    """Relative pose error over pairs ``delta`` apart (all start indices)."""

    delta: float
    unit: str
    trans_rmse_m: float
    trans_mean_m: float
    trans_median_m: float
    trans_max_m: float
    rot_rmse_deg: float
    rot_mean_deg: float
    rot_max_deg: float
    trans_errors_m: np.ndarray = field(repr=False)
    rot_errors_deg: np.ndarray = field(repr=False)
    pairs: np.ndarray = field(repr=False)  # (K, 2)

    @property
    def count(self) -> int:
        return len(self.pairs)


def relative_errors(e: np.ndarray, r: np.ndarray, pairs: np.ndarray) -> np.ndarray:
    """(K, 3) error poses ``(ref_i⁻¹ ref_j)⁻¹ (est_i⁻¹ est_j)`` for the index pairs."""
    i, j = pairs[:, 0], pairs[:, 1]
    d_ref = se2_between(r[i], r[j])
    d_est = se2_between(e[i], e[j])
    return se2_between(d_ref, d_est)


def rpe(
    est_poses,
    ref_poses,
    timestamps_us=None,
    delta: float = 1.0,
    unit: DeltaUnit = "s",
) -> RpeResult:
    """Relative pose error: translation norm and absolute heading of the error pose per pair.

    With ``unit="frames"`` this equals evo's RPE ``all_pairs=True`` (translation_part and
    rotation_angle_deg) on planar trajectories. No alignment is needed (it is invariant to it).
    """
    e, r = _check_pair(est_poses, ref_poses)
    pairs = pairs_for_delta(r, timestamps_us, delta, unit)
    if len(pairs):
        err = relative_errors(e, r, pairs)
        trans = np.linalg.norm(err[:, :2], axis=1)
        rot = np.rad2deg(np.abs(err[:, 2]))
    else:
        trans = rot = np.zeros(0)
    ts, rs = ErrorStats.of(trans), ErrorStats.of(rot)
    return RpeResult(
        delta=float(delta),
        unit=unit,
        trans_rmse_m=ts.rmse,
        trans_mean_m=ts.mean,
        trans_median_m=ts.median,
        trans_max_m=ts.max,
        rot_rmse_deg=rs.rmse,
        rot_mean_deg=rs.mean,
        rot_max_deg=rs.max,
        trans_errors_m=trans,
        rot_errors_deg=rot,
        pairs=pairs,
    )


# --- KITTI-style drift -------------------------------------------------------------------------


@dataclass(frozen=True)
class DriftResult:
    """KITTI odometry metric: mean relative error over sub-sequences of fixed path length.

    ``translation_pct`` is the translation error in % of the segment length and
    ``rotation_deg_per_100m`` the heading error per 100 m, both averaged over every segment of
    every length; NaN (with ``num_segments == 0``) when the run is shorter than every length.
    """

    translation_pct: float
    rotation_deg_per_100m: float
    num_segments: int
    per_length: dict[float, tuple[float, float, int]]  # length -> (pct, deg/100m, count)


def drift(
    est_poses,
    ref_poses,
    segment_lengths_m=(100.0,),
    step_frames: int = 1,
) -> DriftResult:
    """KITTI-style drift: for each start (every ``step_frames``) and length L, the first frame
    whose reference path from the start is >= L; error = |t_err| / L and |yaw_err| / L."""
    e, r = _check_pair(est_poses, ref_poses)
    if isinstance(step_frames, bool) or not isinstance(step_frames, (int, np.integer)):
        raise DataError(
            f"drift: step_frames must be an integer >= 1, got {type(step_frames).__name__} "
            f"{step_frames!r}"
        )
    if step_frames < 1:
        raise DataError(f"drift: step_frames must be >= 1, got {step_frames}")
    if np.ndim(segment_lengths_m) == 0 and not isinstance(segment_lengths_m, str):
        segment_lengths_m = (segment_lengths_m,)  # one length given as a bare number
    try:
        lengths = [float(x) for x in segment_lengths_m]
    except (TypeError, ValueError):
        raise DataError(
            f"drift: segment lengths must be numbers in metres, got {segment_lengths_m!r}"
        ) from None
    if not lengths or any(not np.isfinite(x) or x <= 0 for x in lengths):
        raise DataError(f"drift: segment lengths must be positive, got {list(segment_lengths_m)}")
    dist = path_lengths_m(r)
    starts = np.arange(0, len(r), int(step_frames))
    all_t, all_r = [], []
    per_length = {}
    for length in lengths:
        ends = np.searchsorted(dist, dist[starts] + length - 1e-9, side="left")
        keep = ends < len(r)
        pairs = np.column_stack([starts[keep], ends[keep]])
        if len(pairs):
            err = relative_errors(e, r, pairs)
            t_rel = np.linalg.norm(err[:, :2], axis=1) / length
            r_rel = np.rad2deg(np.abs(err[:, 2])) / length
        else:
            t_rel = r_rel = np.zeros(0)
        all_t.append(t_rel)
        all_r.append(r_rel)
        per_length[length] = (
            float(np.mean(t_rel) * 100) if len(t_rel) else float("nan"),
            float(np.mean(r_rel) * 100) if len(r_rel) else float("nan"),
            len(t_rel),
        )
    t_all, r_all = np.concatenate(all_t), np.concatenate(all_r)
    if t_all.size == 0:
        return DriftResult(float("nan"), float("nan"), 0, per_length)
    return DriftResult(
        translation_pct=float(np.mean(t_all) * 100),
        rotation_deg_per_100m=float(np.mean(r_all) * 100),
        num_segments=int(t_all.size),
        per_length=per_length,
    )


# --- turn scale --------------------------------------------------------------------------------


@dataclass(frozen=True)
class TurnScaleResult:
    """How far the estimate turns per degree the ground truth turns, fitted over every step.

    ``scale`` is the least-squares slope of the estimate's heading change on the ground truth's,
    step by step (above 1: the estimate turns too far; a turn-rate scale error, where
    ``rpe`` and ``drift`` mix turning and drifting). NaN where the ground truth turns less than
    the minimum in all (a straight drive measures no turn). ``steps`` holds the per-step heading
    changes (truth, estimate error; rad) for pooling several sessions with
    :func:`turn_scale_of_steps`."""

    scale: float
    turned_deg: float  # the ground truth's heading change summed in absolute value
    num_steps: int
    steps: tuple[np.ndarray, np.ndarray] = field(repr=False, compare=False)


def turn_scale_of_steps(
    true_steps_rad: np.ndarray, error_steps_rad: np.ndarray, min_turn_deg: float = 45.0
) -> TurnScaleResult:
    """The turn scale of per-step heading changes of the truth and of the estimate's error."""
    dh = np.asarray(true_steps_rad, dtype=np.float64).ravel()
    de = np.asarray(error_steps_rad, dtype=np.float64).ravel()
    if dh.shape != de.shape:
        raise DataError(f"turn scale: {dh.size} truth steps against {de.size} error steps")
    if not np.isfinite(min_turn_deg) or min_turn_deg < 0:
        raise DataError(f"turn scale: the minimum turn must be >= 0 deg, got {min_turn_deg!r}")
    turned = float(np.rad2deg(np.abs(dh).sum()))
    sxx = float(dh @ dh)
    scale = 1.0 + float(dh @ de) / sxx if turned >= max(min_turn_deg, 1e-9) else float("nan")
    return TurnScaleResult(scale=scale, turned_deg=turned, num_steps=int(dh.size), steps=(dh, de))


def turn_scale(est_poses, ref_poses, min_turn_deg: float = 45.0) -> TurnScaleResult:
    """The estimate's turn scale against the reference (see :class:`TurnScaleResult`): the
    heading error's change from pose to pose regressed on the reference's heading change."""
    e, r = _check_pair(est_poses, ref_poses)
    dh = _wrap(np.diff(r[:, 2]))
    de = _wrap(np.diff(_wrap(e[:, 2] - r[:, 2])))
    return turn_scale_of_steps(dh, de, min_turn_deg)


# --- consistency of reported covariances ---------------------------------------------------------


def relative_motion_nees(est_motions, covariances, ref_motions) -> np.ndarray:
    """Normalised estimation error squared of relative motions (4x4 ``prev_from_this``, planar)
    against the reference motions, with their (3, 3) covariances in Pose2 tangent order
    (x, y, yaw; body frame of the later pose). An honest covariance gives a mean of 3.

    The error is ``ref^-1 est`` as (x, y, yaw), a right perturbation in the frame of the later
    pose, as the odometry reports its key-frame covariances; a motion whose covariance is
    singular or non-finite gets NaN."""
    e = to_xy_yaw(np.asarray(est_motions, dtype=np.float64), "estimated motions")
    r = to_xy_yaw(np.asarray(ref_motions, dtype=np.float64), "reference motions")
    cov = np.asarray(covariances, dtype=np.float64)
    if len(e) != len(r) or cov.shape != (len(e), 3, 3):
        raise DataError(
            f"NEES: {len(e)} estimated motions, {len(r)} reference motions and covariances of "
            f"shape {cov.shape}: expected the same count and (N, 3, 3)"
        )
    out = np.full(len(e), np.nan)
    for i in range(len(e)):
        err = se2_between(r[i], e[i])
        if not np.all(np.isfinite(cov[i])):
            continue
        try:
            out[i] = float(err @ np.linalg.solve(cov[i], err))
        except np.linalg.LinAlgError:
            continue
    return out
