"""ScanContext (Kim & Kim, IROS 2018) for 2-D radar point clouds, in numpy.

A polar grid of ``num_rings`` x ``num_sectors`` cells up to ``max_range_m`` around the reference
sensor. Radar points have no height, so the paper's "max z" cell value collapses to occupancy; the
default cell value is ``log1p(points in the cell)``, which keeps the density information that
accumulated radar sweeps carry. Retrieval follows the paper: ring keys (occupied fraction of each
ring, rotation invariant) pick ``num_candidates`` database entries by L2, which are re-ranked by
the column-shift distance

    d(Q, C) = min_n  1/|J| sum_{j in J} (1 - cos(q_j, c_{j+n}))

over the columns J that are non-empty in both (sector shifts make it invariant to yaw).

Radar configuration (vs the AutoPlace reference code's port): metric max range 80 m (where
ARS408 points are dense, instead of 1.414 normalised units of which only ~7 of 20 rings are ever
filled), 20 rings x 60 sectors (3 m x 6 deg cells), point counts instead of binary occupancy.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from radarslam.errors import DataError
from radarslam.place_recognition.config import ScanContextConfig


def scan_context(
    xy: np.ndarray, cfg: ScanContextConfig, rcs01: np.ndarray | None = None
) -> np.ndarray:
    """(num_rings, num_sectors) float32 descriptor of one cloud (points in the sensor frame)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    if xy.size and not np.all(np.isfinite(xy)):
        raise DataError("ScanContext: point coordinates contain NaN or infinity")
    r = np.hypot(xy[:, 0], xy[:, 1])
    keep = r < cfg.max_range_m
    ring = np.minimum((r[keep] / cfg.max_range_m * cfg.num_rings).astype(np.int64),
                      cfg.num_rings - 1)  # fmt: skip
    ang = np.arctan2(xy[keep, 1], xy[keep, 0])  # (-pi, pi]
    sector = np.floor((ang + np.pi) / (2 * np.pi) * cfg.num_sectors).astype(np.int64)
    sector %= cfg.num_sectors
    flat = ring * cfg.num_sectors + sector
    size = cfg.num_rings * cfg.num_sectors
    counts = np.bincount(flat, minlength=size).astype(np.float64)
    if cfg.cell_value == "count":
        cell = np.log1p(counts)
    elif cfg.cell_value == "occupancy":
        cell = (counts > 0).astype(np.float64)
    else:
        if rcs01 is None:
            raise DataError("ScanContext cell_value='rcs' needs per-point RCS values")
        vals = np.asarray(rcs01, dtype=np.float64).reshape(-1)
        if len(vals) != len(xy):
            raise DataError(f"ScanContext: {len(vals)} RCS values for {len(xy)} points")
        cell = np.zeros(size)
        np.maximum.at(cell, flat, 1.0 + np.clip(vals[keep], 0, 1))
    return cell.reshape(cfg.num_rings, cfg.num_sectors).astype(np.float32)


def ring_key(sc: np.ndarray) -> np.ndarray:
    """(..., num_rings) fraction of occupied sectors per ring (rotation invariant)."""
    return (np.asarray(sc) > 0).mean(axis=-1).astype(np.float32)


def shift_distance(query: np.ndarray, candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Column-shift cosine distance of one (R, S) query to (K, R, S) candidates.

    Returns (distance (K,), best sector shift (K,)); a pair without any column that is non-empty
    in both gets distance 1.
    """
    q = np.asarray(query, dtype=np.float64)
    c = np.asarray(candidates, dtype=np.float64)
    n_s = q.shape[1]
    shifts = (np.arange(n_s)[:, None] + np.arange(n_s)[None, :]) % n_s  # (shift, column)
    cs = c[:, :, shifts]  # (K, R, shift, S): candidate column j+n at [.., n, j]
    dot = np.einsum("rj,krnj->knj", q, cs)
    qn = np.linalg.norm(q, axis=0)  # (S,)
    cn = np.linalg.norm(cs, axis=1)  # (K, shift, S)
    valid = (qn[None, None, :] > 0) & (cn > 0)
    cos = np.where(valid, dot / np.where(valid, qn[None, None, :] * cn, 1.0), 0.0)
    nvalid = valid.sum(axis=2)
    sim = np.where(nvalid > 0, cos.sum(axis=2) / np.maximum(nvalid, 1), 0.0)  # (K, shift)
    dist = 1.0 - sim
    best = np.argmin(dist, axis=1)
    return dist[np.arange(len(c)), best], best


@dataclass(frozen=True)
class ScanContextSearch:
    indices: np.ndarray  # (Q, K) rows of the database, best first
    distances: np.ndarray  # (Q, K) column-shift distance (ascending)


class ScanContextIndex:
    """Database of scan contexts with the paper's two-stage search."""

    def __init__(self, cfg: ScanContextConfig | None = None):
        self.cfg = cfg or ScanContextConfig()
        self.contexts = np.zeros((0, self.cfg.num_rings, self.cfg.num_sectors), np.float32)
        self.keys = np.zeros((0, self.cfg.num_rings), np.float32)

    def describe(self, xy: np.ndarray, rcs01: np.ndarray | None = None) -> np.ndarray:
        return scan_context(xy, self.cfg, rcs01)

    def add(self, contexts: np.ndarray) -> None:
        contexts = np.asarray(contexts, dtype=np.float32).reshape(
            -1, self.cfg.num_rings, self.cfg.num_sectors
        )
        self.contexts = np.concatenate([self.contexts, contexts])
        self.keys = np.concatenate([self.keys, ring_key(contexts)])

    def __len__(self) -> int:
        return len(self.contexts)

    def search(self, queries: np.ndarray, k: int) -> ScanContextSearch:
        queries = np.asarray(queries, dtype=np.float32).reshape(
            -1, self.cfg.num_rings, self.cfg.num_sectors
        )
        n_cand = min(max(self.cfg.num_candidates, k), len(self))
        k = min(k, n_cand)
        out_i = np.zeros((len(queries), k), np.int64)
        out_d = np.zeros((len(queries), k), np.float64)
        if len(self) == 0:
            return ScanContextSearch(out_i, out_d)
        qkeys = ring_key(queries)
        for qi, (sc, key) in enumerate(zip(queries, qkeys, strict=True)):
            d2 = np.sum((self.keys - key[None, :]) ** 2, axis=1)
            cand = np.argsort(d2, kind="stable")[:n_cand]
            dist, _ = shift_distance(sc, self.contexts[cand])
            order = np.lexsort((cand, dist))[:k]
            out_i[qi] = cand[order]
            out_d[qi] = dist[order]
        return ScanContextSearch(out_i, out_d)
