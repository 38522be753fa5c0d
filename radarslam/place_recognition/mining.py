"""Hard-negative mining from the descriptor cache, and the triplet loss of one step."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from radarslam.errors import DataError

from .descriptors import FrameStore, _pairwise_l2
from .runtime import _autocast
from .train_config import TrainConfig


@dataclass(frozen=True, eq=False)
class Triplet:
    """One mined training example: frame indices of the query, its positive and hard negatives."""

    query: int
    positive: int
    negatives: np.ndarray  # (k,) int64, 1 <= k <= num_negatives
    turned: bool = False  # the query's images turned by 180 deg, its positive driven reversed


def mine_triplets(
    q_desc: torch.Tensor,
    query_frames: np.ndarray,
    db_desc: torch.Tensor,
    db_frames: np.ndarray,
    data: Any,
    cfg: TrainConfig,
    rng: np.random.Generator,
    turned: bool = False,
) -> tuple[list[Triplet], int]:
    """Mine one triplet per query from the descriptor cache -> (triplets, number skipped).

    ``turned``: ``q_desc`` describe the queries' turned images, whose positives are the ones
    driven the other way round (``data.reversed_positives``)."""
    n_frames = len(data.images)
    row_of = np.full(n_frames, -1, dtype=np.int64)
    row_of[np.asarray(db_frames)] = np.arange(len(db_frames))
    root = getattr(data, "root", "data")
    triplets: list[Triplet] = []
    skipped = 0
    for s in range(0, len(query_frames), 256):
        dist = _pairwise_l2(q_desc[s : s + 256], db_desc).cpu().numpy()
        for i, q in enumerate(query_frames[s : s + 256]):
            q = int(q)
            pos = (
                data.reversed_positives(q, cfg.turned_max_heading_error_deg)
                if turned
                else data.positives(q)
            )
            pos_rows = row_of[np.asarray(pos, dtype=np.int64)]
            neg_pool = row_of[np.asarray(data.negatives_pool(q), dtype=np.int64)]
            if (pos_rows < 0).any() or (neg_pool < 0).any():
                raise DataError(f"{root}: positives/negatives of frame {q} are not database frames")
            if pos_rows.size == 0 or neg_pool.size == 0:
                skipped += 1
                continue
            d = dist[i]
            best = int(np.argmin(d[pos_rows]))
            d_pos = float(d[pos_rows[best]])
            cand = np.unique(rng.choice(neg_pool, size=cfg.neg_sample, replace=True))
            order = np.argsort(d[cand], kind="stable")[: cfg.neg_candidates]
            near = cand[order]
            violating = near[d[near] < d_pos + cfg.margin][: cfg.num_negatives]
            if violating.size == 0:
                skipped += 1
                continue
            triplets.append(
                Triplet(
                    query=q,
                    positive=int(db_frames[pos_rows[best]]),
                    negatives=np.asarray(db_frames)[violating].astype(np.int64),
                    turned=turned,
                )
            )
    return triplets, skipped


def _triplet_step_loss(
    model: torch.nn.Module,
    store: FrameStore,
    sequences: np.ndarray,
    triplets: list[Triplet],
    seq_len: int,
    margin: float,
    total_negatives: int,
    amp: bool = False,
) -> torch.Tensor:
    """Loss of some triplets (sum over (q, p, n_i)) / ``total_negatives`` of the whole batch."""
    frames_per_trip = [np.concatenate(([t.query, t.positive], t.negatives)) for t in triplets]
    seq_frames = np.concatenate(frames_per_trip)
    seqs = np.asarray(sequences)[seq_frames][:, -seq_len:]
    # a turned query's frames are keyed n + frame, apart from the same frames seen unturned
    n = len(store)
    turned_rows = np.concatenate(
        [np.arange(len(f)) == 0 if t.turned else np.zeros(len(f), bool)
         for t, f in zip(triplets, frames_per_trip, strict=True)]
    )  # fmt: skip
    keys = seqs + n * turned_rows[:, None]
    uniq, inverse = np.unique(keys, return_inverse=True)
    seq_index = torch.from_numpy(inverse.reshape(seqs.shape).astype(np.int64)).to(store.device)
    images = store.get(uniq[uniq < n])
    if uniq[-1] >= n:  # sorted: the turned keys come last
        images = torch.cat([images, store.get(uniq[uniq >= n] - n, turned=True)])
    with _autocast(store.device, amp):
        desc = model(images, seq_index)
    desc = desc.float()
    anchors, positives, negatives = [], [], []
    offset = 0
    for t in triplets:
        k = len(t.negatives)
        anchors.append(desc[offset].expand(k, -1))
        positives.append(desc[offset + 1].expand(k, -1))
        negatives.append(desc[offset + 2 : offset + 2 + k])
        offset += 2 + k
    loss = F.triplet_margin_loss(
        torch.cat(anchors), torch.cat(positives), torch.cat(negatives),
        margin=margin, p=2, reduction="sum",
    )  # fmt: skip
    return loss / total_negatives
