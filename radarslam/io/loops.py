"""Loop-closure records (graph node keys, loop verifications and candidates) and the
``loops.csv`` codec.

The SLAM back end writes these and ``radarslam eval`` reads them, so they sit below both; the
module stays free of heavy imports so the evaluator reads ``loops.csv`` without gtsam or open3d.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from radarslam.errors import DataError
from radarslam.geometry import matrix_to_se2, se2_to_matrix
from radarslam.io.atomic import write_text_atomic
from radarslam.io.text import read_text


@dataclass(frozen=True, order=True)
class NodeKey:
    """A key frame of one session (scene): ``index`` counts key frames from 0 within the session."""

    session: str
    index: int

    def __str__(self) -> str:
        return f"{self.session}#{self.index}"


@dataclass(frozen=True, eq=False)
class LoopVerification:
    """Outcome of registering a query key frame's local map against a candidate's."""

    accepted: bool
    reason: str  # "ok" or why it was rejected (names the failed threshold and value)
    candidate_from_query: np.ndarray  # 4x4: the query key frame expressed in the candidate frame
    fitness: float  # fraction of query points with a correspondence within max distance
    inlier_rmse_m: float
    overlap: float  # fraction of occupied cells shared by the two maps after alignment
    information: np.ndarray  # 3x3, Pose2 tangent order (x, y, theta)
    initial_heading_deg: float = float("nan")  # the heading hypothesis that won
    runtime_ms: float = 0.0
    #: fraction of query points with a correspondence within the tight distance (0.3 m)
    tight_fitness: float = float("nan")
    #: smaller / larger eigenvalue of the correspondences' point-to-line normal scatter (1: fully
    #: constrained, near 0: the alignment can slide along a straight street)
    constraint_ratio: float = float("nan")


@dataclass(frozen=True, eq=False)
class LoopCandidate:
    """One place-recognition candidate and what verification made of it (one ``loops.csv`` row)."""

    query: NodeKey
    candidate: NodeKey
    query_timestamp_us: int
    candidate_timestamp_us: int
    descriptor_distance: float
    accepted: bool
    reason: str
    candidate_from_query: np.ndarray = field(default_factory=lambda: np.eye(4))
    fitness: float = float("nan")
    inlier_rmse_m: float = float("nan")
    overlap: float = float("nan")
    tight_fitness: float = float("nan")
    #: what proposed the candidate: "recognition" (AutoPlace), "proximity" (the map),
    #: or "reversed" (AutoPlace's turned images)
    source: str = "recognition"
    constraint_ratio: float = float("nan")

    @staticmethod
    def from_verification(
        query: NodeKey,
        candidate: NodeKey,
        query_timestamp_us: int,
        candidate_timestamp_us: int,
        descriptor_distance: float,
        verification: LoopVerification,
    ) -> LoopCandidate:
        return LoopCandidate(
            query=query,
            candidate=candidate,
            query_timestamp_us=int(query_timestamp_us),
            candidate_timestamp_us=int(candidate_timestamp_us),
            descriptor_distance=float(descriptor_distance),
            accepted=verification.accepted,
            reason=verification.reason,
            candidate_from_query=verification.candidate_from_query,
            fitness=verification.fitness,
            inlier_rmse_m=verification.inlier_rmse_m,
            overlap=verification.overlap,
            tight_fitness=verification.tight_fitness,
            constraint_ratio=verification.constraint_ratio,
        )


LOOPS_CSV_COLUMNS: tuple[str, ...] = (
    "query_session",
    "query_index",
    "query_timestamp_us",
    "candidate_session",
    "candidate_index",
    "candidate_timestamp_us",
    "descriptor_distance",
    "accepted",
    "reason",
    "fitness",
    "inlier_rmse_m",
    "overlap",
    "x_m",
    "y_m",
    "yaw_rad",
    "tight_fitness",
    "source",
    "constraint_ratio",
)
#: Files written before ``tight_fitness``, ``source`` and ``constraint_ratio`` existed are read.
_LOOPS_CSV_COLUMNS_V1 = LOOPS_CSV_COLUMNS[:-3]
_LOOPS_CSV_COLUMNS_V2 = LOOPS_CSV_COLUMNS[:-1]


def write_loops_csv(path: str | Path, loops: list[LoopCandidate]) -> None:
    """Every candidate (accepted and rejected), atomically; (x_m, y_m, yaw_rad) is the planar
    ``candidate_from_query``."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(LOOPS_CSV_COLUMNS)
    for lc in loops:
        x, y, yaw = matrix_to_se2(np.asarray(lc.candidate_from_query, dtype=np.float64))
        w.writerow(
            [
                lc.query.session,
                lc.query.index,
                lc.query_timestamp_us,
                lc.candidate.session,
                lc.candidate.index,
                lc.candidate_timestamp_us,
                repr(float(lc.descriptor_distance)),
                int(bool(lc.accepted)),
                lc.reason,
                repr(float(lc.fitness)),
                repr(float(lc.inlier_rmse_m)),
                repr(float(lc.overlap)),
                repr(float(x)),
                repr(float(y)),
                repr(float(yaw)),
                repr(float(lc.tight_fitness)),
                lc.source,
                repr(float(lc.constraint_ratio)),
            ]
        )
    write_text_atomic(path, buf.getvalue())


def read_loops_csv(path: str | Path) -> list[LoopCandidate]:
    return [lc for _, lc in read_loops_csv_numbered(path)]


def read_loops_csv_numbered(path: str | Path) -> list[tuple[int, LoopCandidate]]:
    """The loops of ``path`` with the line number each was read from (for error messages)."""
    path = Path(path)
    text = read_text(path, "loops file")
    try:
        return _parse_loops_csv(path, text)
    except csv.Error as exc:
        raise DataError(f"{path}: not a loops CSV file ({exc})") from None


def _parse_loops_csv(path: Path, text: str) -> list[tuple[int, LoopCandidate]]:
    with io.StringIO(text, newline="") as fh:
        reader = csv.reader(fh)
        header = next(reader, None)
        columns = tuple(header) if header is not None else ()
        if columns not in (LOOPS_CSV_COLUMNS, _LOOPS_CSV_COLUMNS_V1, _LOOPS_CSV_COLUMNS_V2):
            raise DataError(f"{path}:1: header is not {','.join(LOOPS_CSV_COLUMNS)}")
        out = []
        for lineno, row in enumerate(reader, start=2):
            if not row:
                continue
            if len(row) != len(columns):
                raise DataError(f"{path}:{lineno}: expected {len(columns)} columns, got {len(row)}")
            r = dict(zip(columns, row, strict=True))
            try:
                accepted = {"1": True, "0": False, "true": True, "false": False}[
                    r["accepted"].strip().lower()
                ]
                x, y, yaw = float(r["x_m"]), float(r["y_m"]), float(r["yaw_rad"])
                lc = LoopCandidate(
                    query=NodeKey(r["query_session"], int(r["query_index"])),
                    candidate=NodeKey(r["candidate_session"], int(r["candidate_index"])),
                    query_timestamp_us=int(r["query_timestamp_us"]),
                    candidate_timestamp_us=int(r["candidate_timestamp_us"]),
                    descriptor_distance=float(r["descriptor_distance"]),
                    accepted=accepted,
                    reason=r["reason"],
                    candidate_from_query=se2_to_matrix(x, y, yaw),
                    fitness=float(r["fitness"]),
                    inlier_rmse_m=float(r["inlier_rmse_m"]),
                    overlap=float(r["overlap"]),
                    tight_fitness=float(r.get("tight_fitness", "nan")),
                    source=r.get("source", "recognition"),
                    constraint_ratio=float(r.get("constraint_ratio", "nan")),
                )
            except (ValueError, KeyError):
                raise DataError(f"{path}:{lineno}: malformed loop row {','.join(row)!r}") from None
            if lc.query.index < 0 or lc.candidate.index < 0:
                raise DataError(f"{path}:{lineno}: negative key-frame index in {','.join(row)!r}")
            if accepted and not np.all(np.isfinite([x, y, yaw])):
                raise DataError(f"{path}:{lineno}: accepted loop with non-finite pose")
            out.append((lineno, lc))
    return out
