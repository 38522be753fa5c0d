"""Where a training run executes: the torch device, torch.distributed under torchrun, seeds
and bfloat16 autocast."""

from __future__ import annotations

import contextlib
import os
import random
from dataclasses import dataclass

import numpy as np
import torch

from radarslam.errors import ConfigError

from .config import check_device_name


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


def _autocast(device: torch.device, enabled: bool):
    if enabled and device.type == "cuda":
        return torch.autocast(device_type="cuda", dtype=torch.bfloat16)
    return contextlib.nullcontext()
