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

This module is the loop; the settings are in :mod:`.train_config`, devices and seeding in
:mod:`.runtime`, descriptor passes and recall in :mod:`.descriptors`, mining and the loss in
:mod:`.mining`, and starting from a checkpoint in :mod:`.resume`.
"""

from __future__ import annotations

import contextlib
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

from radarslam.errors import CheckpointError
from radarslam.io.atomic import write_json_atomic

from .checkpoint import save_checkpoint
from .descriptors import (
    FrameStore,
    _check_data,
    _descriptors,
    compute_descriptors,
    recall_at_n_from_descriptors,
)
from .mining import Triplet, _triplet_step_loss, mine_triplets
from .models import ModelConfig, build_model
from .resume import _load_resume_state, init_encoder, init_weights
from .runtime import _Dist, _epoch_rng, _setup_distributed, resolve_device, seed_everything
from .train_config import RESUMABLE_CHANGES, TrainConfig, TrainResult, load_train_config

# callers and tests import these from here
__all__ = [
    "RESUMABLE_CHANGES",
    "FrameStore",
    "TrainConfig",
    "TrainResult",
    "Triplet",
    "_triplet_step_loss",
    "compute_descriptors",
    "init_encoder",
    "load_train_config",
    "mine_triplets",
    "recall_at_n_from_descriptors",
    "resolve_device",
    "seed_everything",
    "train",
]


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
        if train_cfg.init_weights_from and not resume:
            init_weights(net, train_cfg.init_weights_from)
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

        # Turned queries: those (train / val) with positives driven the other way round.
        turn_err = train_cfg.turned_max_heading_error_deg

        def reversed_positives(q: int) -> np.ndarray:
            return data.reversed_positives(q, turn_err)

        def with_reversed(frames: np.ndarray) -> np.ndarray:
            if not train_cfg.turned_queries:
                return np.zeros(0, np.int64)
            return np.flatnonzero([len(reversed_positives(int(q))) > 0 for q in frames])

        turned_train_rows, turned_val_rows = with_reversed(train_frames), with_reversed(val_frames)
        n_turned_train = len(turned_train_rows)

        def turned_pass(with_train: bool) -> tuple[torch.Tensor | None, torch.Tensor | None]:
            """Descriptors of the turned train (if asked) and val queries (None: there are none)."""
            parts = [*([train_frames[turned_train_rows]] if with_train else [])]
            parts.append(val_frames[turned_val_rows])
            frames = np.concatenate(parts)
            if not len(frames):
                return None, None
            desc = _descriptors(
                model, store, sequences, frames, train_cfg.cache_batch_size,
                progress=show, desc="cache (turned)", amp=train_cfg.amp_bf16, turned=True,
            )  # fmt: skip
            tr = desc[:n_turned_train] if with_train and n_turned_train else None
            val = desc[len(desc) - len(turned_val_rows) :] if len(turned_val_rows) else None
            return tr, val

        cache: tuple[torch.Tensor, torch.Tensor | None, torch.Tensor] | None = None
        turned_cache: tuple[torch.Tensor | None, torch.Tensor | None] = (None, None)
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
                turned_cache = turned_pass(with_train=True)
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
            if turned_cache[0] is not None:
                picked = np.isin(turned_train_rows, rows)
                more_triplets, more_skipped = mine_triplets(
                    turned_cache[0][torch.from_numpy(np.flatnonzero(picked)).to(device)],
                    train_frames[turned_train_rows[picked]],
                    db_desc, db_frames, data, train_cfg, rng, turned=True,
                )  # fmt: skip
                triplets += more_triplets
                skipped += more_skipped
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
            turned_recalls: dict[int, float] = {}
            if train_cfg.turned_queries:
                turned_cache = turned_pass(with_train=more)
                if turned_cache[1] is not None:
                    turned_recalls = recall_at_n_from_descriptors(
                        db_desc, turned_cache[1], db_frames, val_frames[turned_val_rows], data,
                        train_cfg.recall_ns, positives=reversed_positives,
                    )  # fmt: skip
                    n_val, n_turned = len(val_frames), len(turned_val_rows)
                    r1 = (n_val * r1 + n_turned * turned_recalls[1]) / (n_val + n_turned)
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
                **{f"val_turned_recall@{n}": v for n, v in turned_recalls.items()},
                **({"val_selection_r1": r1} if turned_recalls else {}),
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
                    **(
                        {"val_turned_recall": {str(n): v for n, v in turned_recalls.items()}}
                        if turned_recalls
                        else {}
                    ),
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
                        f"(skipped {skipped}), val R@1 {recalls[1]:.3f}"
                        + (
                            f", turned {turned_recalls[1]:.3f} (pooled {r1:.3f})"
                            if turned_recalls
                            else ""
                        )
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
