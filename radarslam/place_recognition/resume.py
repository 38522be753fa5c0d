"""Starting a run from a checkpoint: another model's weights or spatial encoder, or this run's
last state."""

from __future__ import annotations

from pathlib import Path

import torch

from radarslam.errors import CheckpointError

from .checkpoint import load_model, read_checkpoint
from .models import ModelConfig
from .train_config import RESUMABLE_CHANGES, TrainConfig


def init_weights(net: torch.nn.Module, path: str | Path) -> int:
    """Copy every weight of checkpoint ``path`` into ``net``; returns the count of tensors.

    The checkpoint must hold the same architecture as ``net`` (its preset label aside); anything
    else is a one-line CheckpointError naming the file and the differing settings.
    """
    cfg = net.cfg
    assert isinstance(cfg, ModelConfig)
    source, _, _ = load_model(path, "cpu", expect=cfg)
    state = source.state_dict()
    net.load_state_dict(state, strict=True)
    return len(state)


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
    want_train = train_cfg.model_dump(mode="json")
    # a key the checkpoint lacks did not exist when it was written: that run had its default
    defaults = TrainConfig.model_construct().model_dump(mode="json")
    have_train = {**defaults, **(payload.get("train_config") or {})}
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
