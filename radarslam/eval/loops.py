"""Loop-closure precision and recall against ground-truth revisits.

- An *accepted* loop is **correct** when its estimated ``candidate_from_query`` agrees with the
  ground-truth relative pose within ``max_translation_error_m`` and ``max_rotation_error_deg``.
  Precision = correct / accepted.
- A key frame is a **GT revisit query** when some key frame processed before it lies within
  ``revisit_radius_m`` (planar ground truth), excluding the recent past of its own pass: frames of
  the same session, or of the sessions its drive continues (``continues``, from ``run.json``),
  less than ``exclude_recent_s`` older. Sessions are processed in the given order
  (default: by first timestamp). Recall = revisit queries with >= 1 correct accepted loop / all
  revisit queries.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from pydantic import Field

from radarslam.config import StrictModel
from radarslam.errors import DataError
from radarslam.eval.metrics import se2_between, to_xy_yaw
from radarslam.geometry import matrix_to_se2
from radarslam.io.loops import LoopCandidate, NodeKey


class LoopEvalConfig(StrictModel):
    revisit_radius_m: float = Field(10.0, gt=0)
    exclude_recent_s: float = Field(30.0, ge=0)
    max_translation_error_m: float = Field(2.0, gt=0)
    max_rotation_error_deg: float = Field(5.0, gt=0)


@dataclass(frozen=True)
class SessionGroundTruth:
    timestamps_us: np.ndarray  # (N,) int64, key frame i at row i
    poses: np.ndarray  # (N, 4, 4) or (N, 3)


@dataclass(frozen=True)
class LoopJudgement:
    loop: LoopCandidate
    translation_error_m: float
    rotation_error_deg: float
    gt_distance_m: float  # planar distance between the two key frames
    correct: bool


@dataclass(frozen=True)
class LoopMetrics:
    num_candidates: int
    num_accepted: int
    num_correct: int
    precision: float  # NaN without accepted loops
    num_revisit_queries: int
    num_recalled_queries: int
    recall: float  # NaN without GT revisits
    candidates_within_radius: int  # candidates (accepted or not) that were true revisits
    judgements: list[LoopJudgement] = field(repr=False, default_factory=list)

    def as_dict(self) -> dict:
        return {
            "num_candidates": self.num_candidates,
            "num_accepted": self.num_accepted,
            "num_correct": self.num_correct,
            "precision": _nan_to_none(self.precision),
            "num_revisit_queries": self.num_revisit_queries,
            "num_recalled_queries": self.num_recalled_queries,
            "recall": _nan_to_none(self.recall),
            "candidates_within_radius": self.candidates_within_radius,
        }


def _nan_to_none(x: float):
    return None if x is None or not np.isfinite(x) else float(x)


class _Lookup:
    def __init__(self, gt: dict[str, SessionGroundTruth]):
        self.xy_yaw = {s: to_xy_yaw(g.poses, f"ground truth of {s}") for s, g in gt.items()}
        self.row = {
            s: {int(t): i for i, t in enumerate(np.asarray(g.timestamps_us))} for s, g in gt.items()
        }

    def pose(self, key: NodeKey, timestamp_us: int, where: str = "loop evaluation") -> np.ndarray:
        rows = self.row.get(key.session)
        if rows is None:
            raise DataError(
                f"{where}: no ground truth for session {key.session!r} (not in this run)"
            )
        i = rows.get(int(timestamp_us))
        if i is None:
            raise DataError(
                f"{where}: key frame {key} at {timestamp_us} us is not in the ground truth"
            )
        if key.index != i:  # the file names one key frame by index and another by time
            raise DataError(
                f"{where}: key frame {key} at {timestamp_us} us is key frame {i} of "
                f"{key.session!r}, not {key.index}"
            )
        return self.xy_yaw[key.session][i]


def judge_loop(
    loop: LoopCandidate, lookup: _Lookup, config: LoopEvalConfig, where: str = "loop evaluation"
) -> LoopJudgement:
    """``where`` starts error messages (e.g. ``loops.csv:12``)."""
    gq = lookup.pose(loop.query, loop.query_timestamp_us, where)
    gc = lookup.pose(loop.candidate, loop.candidate_timestamp_us, where)
    gt_rel = se2_between(gc, gq)  # candidate_from_query
    est_rel = matrix_to_se2(np.asarray(loop.candidate_from_query, dtype=np.float64))
    err = se2_between(gt_rel, est_rel)
    t_err = float(np.hypot(err[0], err[1]))
    r_err = float(np.degrees(abs(err[2])))
    ok = t_err <= config.max_translation_error_m and r_err <= config.max_rotation_error_deg
    return LoopJudgement(loop, t_err, r_err, float(np.hypot(*gt_rel[:2])), bool(ok))


def passes(sessions: Sequence[str], continues: Mapping[str, str] | None) -> dict[str, str]:
    """session -> its pass: the first session of the drive it continues (itself if none)."""
    cont = dict(continues or {})
    out = {}
    for s in sessions:
        root, seen = s, {s}
        while root in cont:
            root = cont[root]
            if root in seen:
                raise DataError(f"loop evaluation: 'continues' loops back through {root!r}")
            seen.add(root)
        out[s] = root
    return out


def gt_revisit_queries(
    gt: dict[str, SessionGroundTruth],
    config: LoopEvalConfig,
    session_order: Sequence[str] | None = None,
    continues: Mapping[str, str] | None = None,
) -> set[NodeKey]:
    """Key frames that revisit a place seen earlier (see module docstring)."""
    from scipy.spatial import cKDTree

    order = list(session_order) if session_order is not None else _chronological(gt)
    missing = [s for s in order if s not in gt]
    if missing:
        raise DataError(f"loop evaluation: sessions {missing} have no ground truth")
    pass_of = passes(order, continues)
    pass_id = {p: i for i, p in enumerate(dict.fromkeys(pass_of.values()))}
    keys: list[NodeKey] = []
    xy, t, rank, drive = [], [], [], []
    for r, s in enumerate(order):
        g = gt[s]
        p = to_xy_yaw(g.poses, f"ground truth of {s}")
        keys += [NodeKey(s, i) for i in range(len(p))]
        xy.append(p[:, :2])
        t.append(np.asarray(g.timestamps_us, dtype=np.int64))
        rank.append(np.full(len(p), r))
        drive.append(np.full(len(p), pass_id[pass_of[s]]))
    if not keys:
        return set()
    xy_all, t_all, rank_all = np.concatenate(xy), np.concatenate(t), np.concatenate(rank)
    drive_all = np.concatenate(drive)
    tree = cKDTree(xy_all)
    exclude_us = round(config.exclude_recent_s * 1e6)
    out = set()
    for n, near in enumerate(tree.query_ball_point(xy_all, config.revisit_radius_m)):
        near = np.asarray(near, dtype=np.int64)
        if near.size == 0:
            continue
        same_pass = drive_all[near] == drive_all[n]
        earlier_session = ~same_pass & (rank_all[near] < rank_all[n])
        same_old = same_pass & (t_all[near] < t_all[n] - exclude_us)
        if np.any(earlier_session | same_old):
            out.add(keys[n])
    return out


def _chronological(gt: dict[str, SessionGroundTruth]) -> list[str]:
    def first(s):
        ts = np.asarray(gt[s].timestamps_us)
        return int(ts.min()) if ts.size else 0

    return sorted(gt, key=lambda s: (first(s), s))


def evaluate_loops(
    loops: Sequence[LoopCandidate],
    gt: dict[str, SessionGroundTruth],
    config: LoopEvalConfig | None = None,
    session_order: Sequence[str] | None = None,
    labels: Sequence[str] | None = None,
    continues: Mapping[str, str] | None = None,
) -> LoopMetrics:
    """``labels[i]`` names where loop ``i`` came from (``path:line``) in error messages;
    ``continues``: session -> the session whose drive it continues (one pass)."""
    config = config or LoopEvalConfig()
    lookup = _Lookup(gt)
    if labels is not None and len(labels) != len(loops):
        raise ValueError(f"{len(labels)} labels for {len(loops)} loops")
    judgements = [
        judge_loop(lp, lookup, config, labels[i] if labels is not None else "loop evaluation")
        for i, lp in enumerate(loops)
    ]
    accepted = [j for j in judgements if j.loop.accepted]
    correct = [j for j in accepted if j.correct]
    revisits = gt_revisit_queries(gt, config, session_order, continues)
    recalled = {j.loop.query for j in correct} & revisits
    return LoopMetrics(
        num_candidates=len(judgements),
        num_accepted=len(accepted),
        num_correct=len(correct),
        precision=len(correct) / len(accepted) if accepted else float("nan"),
        num_revisit_queries=len(revisits),
        num_recalled_queries=len(recalled),
        recall=len(recalled) / len(revisits) if revisits else float("nan"),
        candidates_within_radius=sum(
            j.gt_distance_m <= config.revisit_radius_m for j in judgements
        ),
        judgements=judgements,
    )
