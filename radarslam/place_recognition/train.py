"""AutoPlace training: triplet loss with hard negatives mined from a per-epoch descriptor cache.

Follows the documented behaviour of the AutoPlace reference code:

- every epoch starts from descriptors of all database and train-query sequences computed in eval
  mode (the cache); the end-of-epoch validation pass computes the same descriptors with the same
  weights, so it doubles as the next epoch's cache and each epoch encodes every frame only once;
- positive = the database frame within ``pos_radius_m`` (9 m) nearest in descriptor space;
- negatives: ``neg_sample`` (1000) random draws with replacement from database frames beyond
  ``neg_radius_m`` (18 m), deduplicated, the ``neg_candidates`` (100) nearest in descriptor space,
  those with ``d_neg < d_pos + margin``, the first ``num_negatives`` (10); a query with none is
  skipped this epoch;
- loss: triplet margin loss (margin sqrt(0.1), p=2) summed over (q, p, n_i) and divided by the
  number of negatives in the batch; SGD 0.01 / momentum 0.9 / weight decay 1e-3, StepLR x0.5
  every 5 epochs, batch 8 queries;
- validation recall@N every epoch (database split vs val split, correct = any of the top N within
  ``pos_radius_m``); best checkpoint on val recall@1, only after ``select_after_epoch``; early
  stopping after ``patience`` epochs without improvement (also only counted after that epoch).

Randomness of epoch ``e`` (query subset, negative draws, batch order) comes from a generator seeded
with ``(seed, e)``, so a resumed run mines and orders exactly as an uninterrupted one would.

Multi-GPU: launched by ``torchrun`` (``WORLD_SIZE``/``LOCAL_RANK`` in the environment) the model is
wrapped in DistributedDataParallel, mined queries are sharded with a DistributedSampler, and only
rank 0 writes files. Every rank computes the full cache and validation (identical on all ranks, so
mining and early-stopping decisions agree without communication).
"""

from __future__ import annotations

import contextlib
import math
import os
import random
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import Field, model_validator

from radarslam.config import CONFIG_DIR, StrictModel, load_config
from radarslam.errors import CheckpointError, ConfigError, DataError
from radarslam.io.atomic import write_json_atomic

from .checkpoint import read_checkpoint, save_checkpoint
from .config import check_device_name
from .models import ModelConfig, build_model

# Train-config fields that may change between a run and its resumption: they do not alter what
# the optimisation computes (epochs/patience only move the end, the rest are execution details).
RESUMABLE_CHANGES = frozenset(
    {
        "epochs",
        "patience",
        "time_budget_s",
        "device",
        "threads",
        "cache_batch_size",
        "micro_batch_size",
    }
)


class TrainConfig(StrictModel):
    """Optimisation and mining settings (defaults = the AutoPlace reference)."""

    epochs: int = Field(50, ge=1)
    batch_size: int = Field(8, ge=1)  # queries per optimiser step
    # Queries per forward/backward inside a batch; gradients accumulate to the full batch, so the
    # result equals batch_size but peak memory is that of micro_batch_size (CPU: ~36 frames/query).
    micro_batch_size: int | None = Field(None, ge=1)
    lr: float = Field(0.01, gt=0)
    momentum: float = Field(0.9, ge=0)
    weight_decay: float = Field(1e-3, ge=0)
    lr_step_epochs: int = Field(5, ge=1)
    lr_gamma: float = Field(0.5, gt=0)
    margin: float = Field(math.sqrt(0.1), gt=0)
    num_negatives: int = Field(10, ge=1)
    neg_sample: int = Field(1000, ge=1)
    neg_candidates: int = Field(100, ge=1)
    # Random subset of train queries mined per epoch (None = all); bounds CPU epochs.
    queries_per_epoch: int | None = Field(None, ge=1)
    cache_batch_size: int = Field(32, ge=1)  # frames per forward in descriptor passes
    seed: int = 1234
    device: str = "auto"  # "auto" (cuda if available, else cpu), "cpu", "cuda", "cuda:N"
    # torch intra-op threads (None: torch default). CPU training is bitwise reproducible only with
    # 1 thread: multi-threaded convolution backward sums in a varying order, and the mining's
    # threshold decisions amplify last-bit differences into different triplets a few epochs on.
    threads: int | None = Field(None, ge=1)
    deterministic: bool = True  # cuDNN deterministic kernels
    # bfloat16 autocast of the forward passes on CUDA (loss, mining and the optimiser stay in
    # float32); ignored on CPU, where bf16 convolutions are slower than float32.
    amp_bf16: bool = False
    select_after_epoch: int = Field(25, ge=0)  # best checkpoint only for epochs > this
    patience: int = Field(5, ge=0)  # epochs without val R@1 gain before stopping; 0 = never
    # Wall-clock budget of this call: no new epoch starts once it is spent (checked after each
    # epoch, and only once an epoch past select_after_epoch exists, so a best checkpoint does).
    time_budget_s: float | None = Field(None, gt=0)
    recall_ns: list[int] = Field(default_factory=lambda: [1, 5, 10, 20], min_length=1)
    #: Start the spatial encoder from this checkpoint's (an SE or SE+TE model with the same
    #: encoder layers); the LSTM still starts from scratch. Two-stage training: a compact LSTM
    #: learnt jointly with a randomly initialised trunk settles below the SE alone on DPR'd data.
    #: Ignored when resuming (the run's own weights win).
    init_encoder_from: str | None = None

    @model_validator(mode="after")
    def _check(self) -> TrainConfig:
        if self.select_after_epoch >= self.epochs:
            raise ValueError(
                f"select_after_epoch={self.select_after_epoch} must be below epochs={self.epochs} "
                "(no epoch could be selected as best)"
            )
        check_device_name(self.device)
        if self.amp_bf16 and self.device == "cpu":
            raise ValueError("amp_bf16 needs a CUDA device (device is 'cpu')")
        if 1 not in self.recall_ns or any(n < 1 for n in self.recall_ns):
            raise ValueError(f"recall_ns must be positive and contain 1, got {self.recall_ns}")
        return self


def load_train_config(name_or_path: str | Path, overrides: list[str] | None = None) -> TrainConfig:
    """A preset name (``compact_cpu``) or a YAML path -> TrainConfig."""
    path = Path(name_or_path)
    if not path.suffix:
        path = CONFIG_DIR / "place_recognition" / f"train_{name_or_path}.yaml"
        if not path.is_file():
            raise ConfigError(f"unknown train preset {str(name_or_path)!r} ({path} missing)")
    return load_config(TrainConfig, path, overrides)


@dataclass(frozen=True, eq=False)
class Triplet:
    """One mined training example: frame indices of the query, its positive and hard negatives."""

    query: int
    positive: int
    negatives: np.ndarray  # (k,) int64, 1 <= k <= num_negatives


@dataclass
class TrainResult:
    best_checkpoint: Path
    last_checkpoint: Path
    history: list[dict] = field(default_factory=list)
    best_epoch: int = 0
    best_recall_at_1: float = float("nan")


# --------------------------------------------------------------------------------------------
# Devices, distributed set-up, seeding


def resolve_device(name: str, local_rank: int = 0) -> torch.device:
    """``auto`` / ``cpu`` / ``cuda`` / ``cuda:N`` -> a usable torch device, else ConfigError."""
    try:
        check_device_name(name)
    except ValueError as exc:
        raise ConfigError(str(exc)) from None
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ConfigError(f"device {name!r} requested but CUDA is not available")
        if name == "cuda":
            name = f"cuda:{local_rank}"
        count = torch.cuda.device_count()
        if int(name[5:]) >= count:
            raise ConfigError(f"device {name!r} requested but only {count} CUDA device(s) exist")
    return torch.device(name)


@dataclass(frozen=True)
class _Dist:
    rank: int = 0
    world: int = 1
    local_rank: int = 0
    active: bool = False  # running under torch.distributed
    owns_group: bool = False  # this module initialised the group (and must destroy it)


def _setup_distributed(device_name: str) -> _Dist:
    """torchrun sets WORLD_SIZE/RANK/LOCAL_RANK/MASTER_*; then train under DDP (even world 1)."""
    import torch.distributed as dist

    if "WORLD_SIZE" not in os.environ or "LOCAL_RANK" not in os.environ:
        return _Dist()
    try:
        world = int(os.environ["WORLD_SIZE"])
        rank = int(os.environ.get("RANK", os.environ["LOCAL_RANK"]))
        local_rank = int(os.environ["LOCAL_RANK"])
    except ValueError:
        raise ConfigError("WORLD_SIZE/RANK/LOCAL_RANK are not integers") from None
    owns = False
    if not dist.is_initialized():
        use_cuda = torch.cuda.is_available() and device_name != "cpu"
        if use_cuda:
            torch.cuda.set_device(local_rank)
        dist.init_process_group(backend="nccl" if use_cuda else "gloo", init_method="env://")
        owns = True
    return _Dist(rank=rank, world=world, local_rank=local_rank, active=True, owns_group=owns)


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed % 2**32)  # noqa: NPY002 - seeds third-party code using the legacy API
    torch.manual_seed(seed)


def _epoch_rng(seed: int, epoch: int) -> np.random.Generator:
    return np.random.default_rng([seed % 2**32, epoch])


def _unwrap(model: torch.nn.Module) -> torch.nn.Module:
    return model.module if hasattr(model, "module") else model


def _autocast(device: torch.device, enabled: bool):
    if enabled and device.type == "cuda":
        return torch.autocast(device_type="cuda", dtype=torch.bfloat16)
    return contextlib.nullcontext()


# --------------------------------------------------------------------------------------------
# Data access


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

    def get(self, idx: np.ndarray) -> torch.Tensor:
        if self.tensor is not None:
            sel = torch.from_numpy(np.asarray(idx, dtype=np.int64)).to(self.device)
            return self.tensor.index_select(0, sel).float()
        out = torch.from_numpy(np.ascontiguousarray(self.array[idx]))
        return out.to(self.device, non_blocking=True).float()


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


# --------------------------------------------------------------------------------------------
# Descriptors and recall


def _descriptors(
    model: torch.nn.Module,
    store: FrameStore,
    sequences: np.ndarray,
    indices: np.ndarray,
    batch_size: int,
    progress: bool = False,
    desc: str = "descriptors",
    amp: bool = False,
) -> torch.Tensor:
    """(M, D) descriptors on the store's device; every distinct frame is encoded once."""
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
                feats[s : s + batch_size] = net.encode_frames(store.get(frames[s : s + batch_size]))
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
) -> np.ndarray:
    """(M, D) float32 unit descriptors of the sequences ``data.sequences[indices, -seq_len:]``."""
    net = _unwrap(model)
    dev = torch.device(device) if not isinstance(device, torch.device) else device
    net.to(dev)
    _check_sequences_only(data, net.cfg)
    store = FrameStore(data.images, dev, net.cfg, source=str(getattr(data, "root", "data")))
    out = _descriptors(net, store, data.sequences, np.asarray(indices), batch_size, progress)
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
) -> dict[int, float]:
    """Fraction of queries with a true positive (``data.positives``) among their top-N matches."""
    from .metrics import recall_at_n

    k = min(max(ns), len(db_frames))
    hits = np.zeros((len(query_frames), k), dtype=bool)
    db_frames = np.asarray(db_frames)
    for s in range(0, len(query_frames), 512):
        top = torch.topk(_pairwise_l2(q_desc[s : s + 512], db_desc), k, largest=False).indices
        top = db_frames[top.cpu().numpy()]
        for i, q in enumerate(query_frames[s : s + 512]):
            hits[s + i] = np.isin(top[i], np.asarray(data.positives(int(q))))
    return recall_at_n(hits, ns)


# --------------------------------------------------------------------------------------------
# Hard-negative mining


def mine_triplets(
    q_desc: torch.Tensor,
    query_frames: np.ndarray,
    db_desc: torch.Tensor,
    db_frames: np.ndarray,
    data: Any,
    cfg: TrainConfig,
    rng: np.random.Generator,
) -> tuple[list[Triplet], int]:
    """Mine one triplet per query from the descriptor cache -> (triplets, number skipped)."""
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
            pos_rows = row_of[np.asarray(data.positives(q), dtype=np.int64)]
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
                )
            )
    return triplets, skipped


# --------------------------------------------------------------------------------------------
# One optimisation step


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
    uniq, inverse = np.unique(seqs, return_inverse=True)
    seq_index = torch.from_numpy(inverse.reshape(seqs.shape).astype(np.int64)).to(store.device)
    with _autocast(store.device, amp):
        desc = model(store.get(uniq), seq_index)
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


# --------------------------------------------------------------------------------------------
# The training loop


def _git_commit() -> str | None:
    import subprocess

    try:
        out = subprocess.run(
            ["git", "rev-parse", "HEAD"],
            cwd=Path(__file__).resolve().parent,
            capture_output=True,
            text=True,
            timeout=5,
        )
    except (OSError, subprocess.SubprocessError):
        return None
    return out.stdout.strip() or None if out.returncode == 0 else None


def train(
    train_cfg: TrainConfig,
    model_cfg: ModelConfig,
    data: Any,
    out_dir: str | Path,
    resume: bool = False,
    progress: bool = True,
) -> TrainResult:
    """Train ``model_cfg`` on prepared data; writes ``best.pt``, ``last.pt`` and ``history.json``.

    ``resume``: continue from ``out_dir/last.pt`` (its configs must match, except the fields in
    RESUMABLE_CHANGES); a missing or mismatched last checkpoint is a CheckpointError. Without
    ``resume`` a previous run's ``best.pt``, ``last.pt`` and ``history.json`` in ``out_dir`` are
    deleted before the first epoch, so that the directory never mixes two runs (``radarslam pr
    train`` refuses such a directory unless ``--overwrite`` or ``--resume`` is given).
    """
    from tqdm.auto import tqdm

    from .outputs import check_output_dir

    out_dir = check_output_dir(out_dir)
    last_path, best_path = out_dir / "last.pt", out_dir / "best.pt"
    _check_data(data, model_cfg)
    dist_info = _setup_distributed(train_cfg.device)
    threads_before = torch.get_num_threads()
    try:
        device = resolve_device(train_cfg.device, dist_info.local_rank)
        if train_cfg.threads:
            torch.set_num_threads(train_cfg.threads)
        if device.type == "cuda":
            torch.backends.cudnn.deterministic = train_cfg.deterministic
            # Never cuDNN autotuning: every batch has a different number of distinct frames, and
            # re-tuning for each new shape made paper-size steps ~10x slower on an H100.
            torch.backends.cudnn.benchmark = False
        is_main = dist_info.rank == 0
        show = progress and is_main
        seed_everything(train_cfg.seed)

        # channels_last: oneDNN (CPU) and cuDNN (GPU) convolutions run faster in NHWC; measured
        # 1.5-1.8x for a compact training step on 2 CPU threads.
        net = build_model(model_cfg)
        if train_cfg.init_encoder_from and not resume:
            init_encoder(net, train_cfg.init_encoder_from)
        net = net.to(device, memory_format=torch.channels_last)
        optimizer = torch.optim.SGD(
            net.parameters(),
            lr=train_cfg.lr,
            momentum=train_cfg.momentum,
            weight_decay=train_cfg.weight_decay,
        )
        scheduler = torch.optim.lr_scheduler.StepLR(
            optimizer, step_size=train_cfg.lr_step_epochs, gamma=train_cfg.lr_gamma
        )
        history: list[dict] = []
        start_epoch, best_r1, best_epoch, bad_epochs = 1, -1.0, 0, 0
        if resume:
            state = _load_resume_state(last_path, model_cfg, train_cfg)
            net.load_state_dict(
                {k: v.float() if v.is_floating_point() else v for k, v in state["weights"].items()}
            )
            optimizer.load_state_dict(state["optimizer"])
            scheduler.load_state_dict(state["scheduler"])
            history = list(state["history"])
            start_epoch = int(state["epoch"]) + 1
            best_r1, best_epoch = float(state["best_r1"]), int(state["best_epoch"])
            bad_epochs = int(state["bad_epochs"])
            if best_epoch and not best_path.is_file():
                raise CheckpointError(f"{best_path}: missing, but {last_path} records a best epoch")

        model: torch.nn.Module = net
        if dist_info.active:
            from torch.nn.parallel import DistributedDataParallel

            model = DistributedDataParallel(
                net, device_ids=[device.index] if device.type == "cuda" else None
            )

        root = str(getattr(data, "root", "data"))
        store = FrameStore(data.images, device, model_cfg, source=root)
        sequences = np.asarray(data.sequences)
        db_frames = np.asarray(data.splits["database"], dtype=np.int64)
        train_frames = np.asarray(data.splits["train"], dtype=np.int64)
        val_frames = np.asarray(data.splits["val"], dtype=np.int64)
        n_db, n_train = len(db_frames), len(train_frames)
        commit = _git_commit() if is_main else None
        micro = train_cfg.micro_batch_size or train_cfg.batch_size

        def cache_pass(with_train: bool) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
            """Descriptors of DB (+ train) + val in one pass with shared frames encoded once."""
            parts = [db_frames, *([train_frames] if with_train else []), val_frames]
            desc = _descriptors(
                model, store, sequences, np.concatenate(parts), train_cfg.cache_batch_size,
                progress=show, desc="cache", amp=train_cfg.amp_bf16,
            )  # fmt: skip
            db = desc[:n_db]
            tr = desc[n_db : n_db + n_train] if with_train else None
            return db, tr, desc[len(desc) - len(val_frames) :]

        cache: tuple[torch.Tensor, torch.Tensor | None, torch.Tensor] | None = None
        if not resume and is_main:
            # a new run: the previous run's outputs must not survive next to this one's
            for stale in (best_path, last_path, out_dir / "history.json"):
                stale.unlink(missing_ok=True)
        t_start = time.perf_counter()
        for epoch in range(start_epoch, train_cfg.epochs + 1):
            t0 = time.perf_counter()
            rng = _epoch_rng(train_cfg.seed, epoch)
            if cache is None:
                cache = cache_pass(with_train=True)
            db_desc, tr_desc, _ = cache
            rows = np.arange(n_train)
            if train_cfg.queries_per_epoch and train_cfg.queries_per_epoch < n_train:
                rows = np.sort(rng.choice(n_train, train_cfg.queries_per_epoch, replace=False))
            triplets, skipped = mine_triplets(
                tr_desc[torch.from_numpy(rows).to(device)],
                train_frames[rows],
                db_desc,
                db_frames,
                data,
                train_cfg,
                rng,
            )
            # No triplet at all (every query already separates its negatives by the margin) is
            # a legitimate, converged state on easy data: the epoch then makes no step but is
            # still validated and counted for selection, patience and the LR schedule.
            # The order is the DistributedSampler's (seeded by seed + epoch) in both modes, so a
            # one-process DDP run is step-for-step the plain run.
            from torch.utils.data import DistributedSampler

            sampler = DistributedSampler(
                range(len(triplets)),
                num_replicas=dist_info.world,
                rank=dist_info.rank,
                shuffle=True,
                seed=train_cfg.seed,
            )
            sampler.set_epoch(epoch)
            order = np.fromiter(iter(sampler), dtype=np.int64)
            batches = [
                order[s : s + train_cfg.batch_size]
                for s in range(0, len(order), train_cfg.batch_size)
            ]
            model.train()
            lr_epoch = optimizer.param_groups[0]["lr"]
            losses = []
            bar = tqdm(
                batches, desc=f"epoch {epoch}/{train_cfg.epochs}", disable=not show, leave=False
            )
            for batch in bar:
                trips = [triplets[i] for i in batch]
                total_neg = sum(len(t.negatives) for t in trips)
                optimizer.zero_grad(set_to_none=True)
                batch_loss = 0.0
                chunks = [trips[s : s + micro] for s in range(0, len(trips), micro)]
                for ci, chunk in enumerate(chunks):
                    sync = ci == len(chunks) - 1
                    ctx = (
                        model.no_sync()
                        if dist_info.active and not sync
                        else contextlib.nullcontext()
                    )
                    with ctx:
                        loss = _triplet_step_loss(
                            model, store, sequences, chunk, model_cfg.seq_len,
                            train_cfg.margin, total_neg, amp=train_cfg.amp_bf16,
                        )  # fmt: skip
                        loss.backward()
                    batch_loss += float(loss.detach())
                optimizer.step()
                losses.append(batch_loss)
                bar.set_postfix(loss=f"{batch_loss:.4f}")
            with warnings.catch_warnings():
                # An epoch without triplets makes no optimiser step; the per-epoch schedule must
                # still advance (torch warns about the order, which does not matter for StepLR).
                warnings.filterwarnings("ignore", message="Detected call of `lr_scheduler.step")
                scheduler.step()

            more = epoch < train_cfg.epochs
            cache = cache_pass(with_train=more)
            db_desc, _, val_desc = cache
            recalls = recall_at_n_from_descriptors(
                db_desc, val_desc, db_frames, val_frames, data, train_cfg.recall_ns
            )
            r1 = recalls[1]
            record = {
                "epoch": epoch,
                "lr": lr_epoch,
                "loss": float(np.mean(losses)) if losses else None,
                "triplets": len(triplets),
                "skipped_queries": skipped,
                "mean_negatives": float(np.mean([len(t.negatives) for t in triplets]))
                if triplets
                else 0.0,
                **{f"val_recall@{n}": v for n, v in recalls.items()},
                "seconds": round(time.perf_counter() - t0, 2),
            }
            history.append(record)
            improved = False
            if epoch > train_cfg.select_after_epoch:
                if r1 > best_r1:
                    best_r1, best_epoch, bad_epochs, improved = r1, epoch, 0, True
                else:
                    bad_epochs += 1
            if is_main:
                meta = {
                    "epoch": epoch,
                    "val_recall": {str(n): v for n, v in recalls.items()},
                    "git_commit": commit,
                    "data_root": root,
                    "n_database": n_db,
                    "n_train": n_train,
                    "n_val": len(val_frames),
                }
                if improved:
                    save_checkpoint(best_path, net, model_cfg, train_cfg, meta)
                save_checkpoint(
                    last_path, net, model_cfg, train_cfg,
                    {**meta, "best_epoch": best_epoch},
                    training_state={
                        "epoch": epoch,
                        "optimizer": optimizer.state_dict(),
                        "scheduler": scheduler.state_dict(),
                        "history": history,
                        "best_r1": best_r1,
                        "best_epoch": best_epoch,
                        "bad_epochs": bad_epochs,
                    },
                )  # fmt: skip
                write_json_atomic(out_dir / "history.json", history)
                if show:
                    tqdm.write(
                        f"epoch {epoch}: loss {record['loss'] or 0.0:.4f}, "
                        f"triplets {len(triplets)} "
                        f"(skipped {skipped}), val R@1 {r1:.3f}"
                        + (" *best*" if improved else "")
                        + f", {record['seconds']:.1f} s"
                    )
            if dist_info.active:
                torch.distributed.barrier()
            if train_cfg.patience and bad_epochs >= train_cfg.patience:
                break
            if _budget_spent(train_cfg, t_start, best_epoch, dist_info, device):
                if show:
                    tqdm.write(f"time budget of {train_cfg.time_budget_s:.0f} s spent: stopping")
                break
        if best_epoch == 0:
            raise CheckpointError(f"{out_dir}: no epoch after select_after_epoch was validated")
        return TrainResult(
            best_checkpoint=best_path,
            last_checkpoint=last_path,
            history=history,
            best_epoch=best_epoch,
            best_recall_at_1=best_r1,
        )
    finally:
        torch.set_num_threads(threads_before)
        if dist_info.owns_group:
            torch.distributed.destroy_process_group()


def _budget_spent(
    cfg: TrainConfig, t_start: float, best_epoch: int, dist_info: _Dist, device: torch.device
) -> bool:
    """Whether the time budget is spent; rank 0 decides for all ranks (clocks differ)."""
    if cfg.time_budget_s is None:
        return False
    spent = best_epoch > 0 and time.perf_counter() - t_start >= cfg.time_budget_s
    if dist_info.active:
        flag = torch.tensor([1.0 if spent else 0.0], device=device)
        torch.distributed.broadcast(flag, src=0)
        spent = bool(flag.item() > 0)
    return spent


def init_encoder(net: torch.nn.Module, path: str | Path) -> int:
    """Copy the spatial encoder's weights of checkpoint ``path`` into ``net``; returns the count.

    The encoders must match layer for layer (same widths, convolutions per block, input channels
    and normalisation); anything else is a one-line CheckpointError naming the file.
    """
    payload = read_checkpoint(path)
    stored = {k: v for k, v in payload["state_dict"].items() if k.startswith("encoder.")}
    own = {k: v for k, v in net.state_dict().items() if k.startswith("encoder.")}
    src = payload["model_config"]
    mismatch = [
        f"{key}: {src.get(key)!r} != {getattr(net.cfg, key)!r}"
        for key in ("widths", "convs_per_block", "in_channels", "input_norm", "image_size_px")
        if src.get(key) != getattr(net.cfg, key)
    ]
    if mismatch or set(stored) != set(own):
        detail = "; ".join(mismatch) or "different encoder layers"
        raise CheckpointError(f"{path}: encoder does not match the model being trained ({detail})")
    net.load_state_dict({k: v.float() for k, v in stored.items()}, strict=False)
    return len(stored)


def _load_resume_state(path: Path, model_cfg: ModelConfig, train_cfg: TrainConfig) -> dict:
    payload = read_checkpoint(path)
    state = payload.get("training_state")
    if not state:
        raise CheckpointError(f"{path}: holds no training state to resume from")
    have_model = payload["model_config"]
    if have_model != model_cfg.model_dump(mode="json"):
        diff = [k for k in have_model if have_model.get(k) != model_cfg.model_dump().get(k)]
        raise CheckpointError(f"{path}: model config differs from the run's ({', '.join(diff)})")
    have_train = dict(payload.get("train_config") or {})
    want_train = train_cfg.model_dump(mode="json")
    diff = [
        k
        for k in sorted(set(have_train) | set(want_train))
        if k not in RESUMABLE_CHANGES and have_train.get(k) != want_train.get(k)
    ]
    if diff:
        raise CheckpointError(
            f"{path}: train config differs from the run's in {', '.join(diff)} (cannot resume)"
        )
    return {**state, "weights": payload["state_dict"]}
