"""RCS Histogram Re-ranking (RCSHR, AutoPlace paper Sec. III-D, as its reference code does it).

For each query, the top-M candidates by descriptor distance d are re-scored with
``alpha * KL(h_query || h_candidate) + (1 - alpha) * d`` where h are histograms of the per-frame
min-max-normalised RCS values with bin edges ``b_m, b_m + b_w, ...`` (last edge < 1). Values
outside [first edge, last edge] are ignored, 1e-5 is added to every count and each histogram is
normalised to sum 1. There is no other normalisation of the two terms (as in the reference).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from radarslam.errors import ConfigError
from radarslam.place_recognition.config import RerankConfig


def bin_edges(bin_min: float, bin_width: float) -> np.ndarray:
    """Edges b_m + k * b_w for every k with edge < 1 (robust to float steps, unlike arange)."""
    if bin_width <= 0 or not (0.0 <= bin_min < 1.0):
        raise ConfigError(f"RCS histogram needs 0 <= bin_min < 1 and bin_width > 0, got "
                          f"bin_min={bin_min}, bin_width={bin_width}")  # fmt: skip
    n = int(np.floor((1.0 - bin_min) / bin_width - 1e-9)) + 1
    edges = bin_min + bin_width * np.arange(n)
    if len(edges) < 2:
        raise ConfigError(
            f"bin_min={bin_min}, bin_width={bin_width} leave no histogram bin below 1.0"
        )
    return edges


def rcs_histogram(rcs01: np.ndarray, edges: np.ndarray, epsilon: float = 1e-5) -> np.ndarray:
    """Normalised histogram (len(edges) - 1,) of [0, 1] RCS values, epsilon added to each count."""
    counts, _ = np.histogram(np.asarray(rcs01, dtype=np.float64), bins=edges)
    h = counts.astype(np.float64) + epsilon
    return h / h.sum()


def rcs_histograms(rcs_list: Sequence[np.ndarray], cfg: RerankConfig) -> np.ndarray:
    """(N, B) histograms of many frames."""
    edges = bin_edges(cfg.bin_min, cfg.bin_width)
    if len(rcs_list) == 0:
        return np.zeros((0, len(edges) - 1))
    return np.stack([rcs_histogram(r, edges, cfg.epsilon) for r in rcs_list])


def kl_divergence(q: np.ndarray, c: np.ndarray) -> np.ndarray:
    """KL(q || c) = sum q log(q / c) along the last axis (broadcasting; inputs strictly > 0)."""
    q = np.asarray(q, dtype=np.float64)
    c = np.asarray(c, dtype=np.float64)
    return np.sum(q * (np.log(q) - np.log(c)), axis=-1)


@dataclass(frozen=True)
class RerankResult:
    indices: np.ndarray  # (Q, M) candidate indices (into the database), best first
    scores: np.ndarray  # (Q, M) combined score, ascending
    distances: np.ndarray  # (Q, M) the descriptor distance of each re-ordered candidate


def rerank(
    candidate_indices: np.ndarray,
    candidate_distances: np.ndarray,
    query_hists: np.ndarray,
    db_hists: np.ndarray,
    alpha: float,
) -> RerankResult:
    """Re-order each query's candidates by ``alpha * KL + (1 - alpha) * d`` (stable on ties)."""
    idx = np.asarray(candidate_indices)
    dist = np.asarray(candidate_distances, dtype=np.float64)
    if idx.shape != dist.shape or idx.ndim != 2:
        raise ConfigError(f"candidate indices {idx.shape} and distances {dist.shape} must match")
    if len(query_hists) != len(idx):
        raise ConfigError(f"{len(query_hists)} query histograms for {len(idx)} queries")
    kl = kl_divergence(np.asarray(query_hists)[:, None, :], np.asarray(db_hists)[idx])
    score = alpha * kl + (1.0 - alpha) * dist
    order = np.argsort(score, axis=1, kind="stable")
    return RerankResult(
        indices=np.take_along_axis(idx, order, axis=1),
        scores=np.take_along_axis(score, order, axis=1),
        distances=np.take_along_axis(dist, order, axis=1),
    )
