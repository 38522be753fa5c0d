"""Descriptors of prepared frames under a model, and recall@N from them.

:class:`FrameStore` holds the occupancy images on the compute device; descriptor passes encode
every distinct frame of the requested sequences once. Used by training (its per-epoch cache and
validation) and by evaluation.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from radarslam.errors import DataError

from .models import ModelConfig
from .runtime import _autocast


def _unwrap(model: torch.nn.Module) -> torch.nn.Module:
    return model.module if hasattr(model, "module") else model


class FrameStore:
    """Occupancy images as (U, C, H, W) float tensors on the compute device.

    On CUDA the whole uint8 stack is uploaded once when it fits (gathers then run on the GPU);
    otherwise frames are gathered from the numpy array per batch.
    """

    def __init__(self, images: Any, device: torch.device, cfg: ModelConfig, source: str = "data"):
        arr = images if isinstance(images, np.ndarray) else np.asarray(images)
        if arr.ndim == 3:
            arr = arr[:, None]
        if arr.ndim != 4:
            raise DataError(f"{source}: images must be (N, H, W) or (N, C, H, W), got {arr.shape}")
        want = (cfg.in_channels, cfg.image_size_px, cfg.image_size_px)
        if arr.shape[1:] != want:
            raise DataError(
                f"{source}: images are {arr.shape[1:]} per frame but the model expects {want}"
            )
        if arr.size and (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
            lo, hi = float(arr.min()), float(arr.max())
            if lo < 0 or hi > 1:
                raise DataError(
                    f"{source}: image values must be occupancy in [0, 1], got [{lo:g}, {hi:g}]"
                )
        else:
            raise DataError(f"{source}: images have non-numeric dtype {arr.dtype}")
        self.array = arr
        self.device = device
        self.tensor: torch.Tensor | None = None
        if device.type == "cuda":
            free, _ = torch.cuda.mem_get_info(device)
            if arr.nbytes < 0.3 * free:
                self.tensor = torch.from_numpy(np.ascontiguousarray(arr)).to(device)

    def __len__(self) -> int:
        return len(self.array)

    def get(self, idx: np.ndarray, turned: bool = False) -> torch.Tensor:
        """Frames ``idx`` as floats; ``turned``: as seen turned by 180 deg (:func:`turn_images`)."""
        if self.tensor is not None:
            sel = torch.from_numpy(np.asarray(idx, dtype=np.int64)).to(self.device)
            out = self.tensor.index_select(0, sel).float()
        else:
            out = torch.from_numpy(np.ascontiguousarray(self.array[idx]))
            out = out.to(self.device, non_blocking=True).float()
        return turn_images(out) if turned else out


def turn_images(images: torch.Tensor) -> torch.Tensor:
    """Images (..., H, W) as rasterised (:func:`~.image.rasterise`) from their points turned by
    180 deg about the sensor, (x, y) -> (-x, -y), exactly but for points on a pixel boundary
    (rounding half up is not symmetric): pixel (r, c) moves to
    (2 (H // 2) - r, 2 (W // 2) - c), so an even-sized image is mirrored about its centre pixel
    and its first row and column stay empty. AutoPlace's turned search in SLAM queries such
    images for a street driven the other way round."""
    h, w = images.shape[-2:]
    dr, dc = 2 * (h // 2) - (h - 1), 2 * (w // 2) - (w - 1)
    flipped = images.flip(-2, -1)
    out = torch.zeros_like(images)
    out[..., dr:, dc:] = flipped[..., : h - dr, : w - dc]
    return out


def _check_data(data: Any, cfg: ModelConfig) -> None:
    root = getattr(data, "root", "data")
    for name in ("images", "positions_xy", "sequences", "splits"):
        if not hasattr(data, name):
            raise DataError(f"{root}: prepared data lacks '{name}'")
    seq = np.asarray(data.sequences)
    n = len(data.images)
    if seq.ndim != 2 or len(seq) != n:
        raise DataError(f"{root}: sequences must be (N={n}, L), got {seq.shape}")
    if seq.shape[1] < cfg.seq_len:
        raise DataError(
            f"{root}: sequences hold {seq.shape[1]} frames but the model needs {cfg.seq_len}"
        )
    if seq.size and (seq.min() < 0 or seq.max() >= n):
        raise DataError(f"{root}: sequences index frames outside [0, {n})")
    for split in ("database", "train", "val"):
        idx = np.asarray(data.splits.get(split, []))
        if idx.size == 0:
            raise DataError(f"{root}: split '{split}' is empty or missing")
        if idx.min() < 0 or idx.max() >= n:
            raise DataError(f"{root}: split '{split}' indexes frames outside [0, {n})")


def _descriptors(
    model: torch.nn.Module,
    store: FrameStore,
    sequences: np.ndarray,
    indices: np.ndarray,
    batch_size: int,
    progress: bool = False,
    desc: str = "descriptors",
    amp: bool = False,
    turned: bool = False,
) -> torch.Tensor:
    """(M, D) descriptors on the store's device; every distinct frame is encoded once.
    ``turned``: of the sequences' images turned by 180 deg (:func:`turn_images`)."""
    from tqdm.auto import tqdm

    net = _unwrap(model)
    seq_len = net.cfg.seq_len
    seqs = np.asarray(sequences)[np.asarray(indices, dtype=np.int64)][:, -seq_len:]
    frames, inverse = np.unique(seqs, return_inverse=True)
    inverse = torch.from_numpy(inverse.reshape(seqs.shape).astype(np.int64)).to(store.device)
    was_training = net.training
    net.eval()
    try:
        with torch.no_grad(), _autocast(store.device, amp):
            feats = torch.empty((len(frames), net.cfg.frame_feature_dim()), device=store.device)
            starts = range(0, len(frames), batch_size)
            for s in tqdm(starts, desc=desc, disable=not progress, leave=False, unit="batch"):
                feats[s : s + batch_size] = net.encode_frames(
                    store.get(frames[s : s + batch_size], turned=turned)
                )
            out = torch.empty((len(seqs), net.cfg.output_dim()), device=store.device)
            agg = max(batch_size, 256)
            for s in range(0, len(seqs), agg):
                out[s : s + agg] = net.aggregate(feats[inverse[s : s + agg]])
    finally:
        net.train(was_training)
    return out


def compute_descriptors(
    model: torch.nn.Module,
    data: Any,
    indices: np.ndarray,
    batch_size: int = 32,
    device: str | torch.device = "cpu",
    progress: bool = False,
    turned: bool = False,
) -> np.ndarray:
    """(M, D) float32 unit descriptors of the sequences ``data.sequences[indices, -seq_len:]``
    (``turned``: of their images turned by 180 deg)."""
    net = _unwrap(model)
    dev = torch.device(device) if not isinstance(device, torch.device) else device
    net.to(dev)
    _check_sequences_only(data, net.cfg)
    store = FrameStore(data.images, dev, net.cfg, source=str(getattr(data, "root", "data")))
    out = _descriptors(
        net, store, data.sequences, np.asarray(indices), batch_size, progress, turned=turned
    )
    return out.float().cpu().numpy()


def _check_sequences_only(data: Any, cfg: ModelConfig) -> None:
    seq = np.asarray(data.sequences)
    root = getattr(data, "root", "data")
    if seq.ndim != 2 or seq.shape[1] < cfg.seq_len:
        raise DataError(f"{root}: sequences {seq.shape} hold fewer than {cfg.seq_len} frames")


def _pairwise_l2(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Euclidean distances between rows of a and b (unit vectors: sqrt(2 - 2 a.b), clamped)."""
    sq = (a * a).sum(1, keepdim=True) + (b * b).sum(1)[None] - 2.0 * a @ b.T
    return sq.clamp_min_(0).sqrt_()


def recall_at_n_from_descriptors(
    db_desc: torch.Tensor,
    q_desc: torch.Tensor,
    db_frames: np.ndarray,
    query_frames: np.ndarray,
    data: Any,
    ns: list[int],
    positives: Callable[[int], np.ndarray] | None = None,
) -> dict[int, float]:
    """Fraction of queries with a true positive (``positives``, by default ``data.positives``)
    among their top-N matches."""
    from .metrics import recall_at_n

    positives_of = data.positives if positives is None else positives
    k = min(max(ns), len(db_frames))
    hits = np.zeros((len(query_frames), k), dtype=bool)
    db_frames = np.asarray(db_frames)
    for s in range(0, len(query_frames), 512):
        top = torch.topk(_pairwise_l2(q_desc[s : s + 512], db_desc), k, largest=False).indices
        top = db_frames[top.cpu().numpy()]
        for i, q in enumerate(query_frames[s : s + 512]):
            hits[s + i] = np.isin(top[i], np.asarray(positives_of(int(q))))
    return recall_at_n(hits, ns)
