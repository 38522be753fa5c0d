"""Model checkpoints that carry the configs that made them, written atomically and verified on load.

File layout (a ``torch.save`` dict, loaded with ``weights_only=True`` so no pickled code runs):

- ``format`` / ``version``: identify the file,
- ``model_config`` / ``train_config``: plain dicts of the pydantic configs,
- ``state_dict``: the weights, stored as float32 or float16 (``dtype``); loaded back as float32,
- ``digest``: SHA-256 over the stored weights, so a flipped byte in tensor data is caught,
- ``meta``: free JSON-like information (validation numbers, git commit, epoch ...),
- ``training_state``: optimiser/scheduler/epoch state for resuming (training checkpoints only).

Every failure on load (missing, truncated, not a checkpoint, wrong architecture, weights that do not
fit) is a one-line :class:`CheckpointError` naming the file.
"""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

import torch
from pydantic import BaseModel, ValidationError

from radarslam.errors import CheckpointError
from radarslam.io.atomic import atomic_path
from radarslam.place_recognition.archive import check_archive

from .models import ModelConfig, build_model

FORMAT = "radarslam.autoplace"
VERSION = 1


def _unwrap(model: torch.nn.Module) -> torch.nn.Module:
    return model.module if hasattr(model, "module") else model


def _digest(state: dict[str, torch.Tensor]) -> str:
    h = hashlib.sha256()
    for key in sorted(state):
        t = state[key].detach().cpu().contiguous()
        h.update(key.encode())
        h.update(str(t.dtype).encode())
        h.update(str(tuple(t.shape)).encode())
        h.update(t.view(torch.uint8).numpy().tobytes() if t.numel() else b"")
    return h.hexdigest()


def _as_dict(cfg: BaseModel | dict | None) -> dict | None:
    if cfg is None or isinstance(cfg, dict):
        return cfg
    return cfg.model_dump(mode="json")


def save_checkpoint(
    path: str | Path,
    model: torch.nn.Module,
    model_cfg: ModelConfig,
    train_cfg: BaseModel | dict | None = None,
    meta: dict[str, Any] | None = None,
    *,
    half: bool = False,
    training_state: dict[str, Any] | None = None,
) -> Path:
    """Write ``model`` with its configs to ``path`` atomically; ``half`` stores float16 weights."""
    path = Path(path)
    dtype = torch.float16 if half else torch.float32
    # Stored contiguous (NCHW), whatever memory format the model runs in.
    state = {
        k: (v.detach().to("cpu", dtype) if v.is_floating_point() else v.detach().cpu())
        .contiguous()
        .clone()
        for k, v in _unwrap(model).state_dict().items()
    }
    payload = {
        "format": FORMAT,
        "version": VERSION,
        "model_config": model_cfg.model_dump(mode="json"),
        "train_config": _as_dict(train_cfg),
        "dtype": str(dtype).removeprefix("torch."),
        "state_dict": state,
        "digest": _digest(state),
        "meta": dict(meta or {}),
        "training_state": training_state,
    }
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
    return path


def _first_sentence(exc: BaseException, limit: int = 120) -> str:
    """The first sentence of an exception message, cut at a word boundary."""
    text = " ".join(str(exc).split())
    if ". " in text:
        text = text[: text.index(". ")]
    if len(text) > limit:
        text = text[:limit].rsplit(" ", 1)[0] + " ..."
    return text


def read_checkpoint(path: str | Path, device: str | torch.device = "cpu") -> dict[str, Any]:
    """The verified payload of a checkpoint (weights still in their stored dtype)."""
    path = Path(path)
    if not path.exists():
        raise CheckpointError(f"{path}: checkpoint file does not exist")
    check_archive(path)
    try:
        payload = torch.load(path, map_location=device, weights_only=True)
    except Exception as exc:  # torch raises many types for truncated/garbled zips
        raise CheckpointError(
            f"{path}: not a readable checkpoint ({type(exc).__name__}: {_first_sentence(exc)})"
        ) from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise CheckpointError(f"{path}: not a radarslam AutoPlace checkpoint (no '{FORMAT}' tag)")
    if payload.get("version") != VERSION:
        raise CheckpointError(
            f"{path}: checkpoint version {payload.get('version')!r} is not supported "
            f"(this code reads version {VERSION})"
        )
    for key in ("model_config", "state_dict", "digest"):
        if key not in payload:
            raise CheckpointError(f"{path}: checkpoint lacks '{key}'")
    state = payload["state_dict"]
    if not isinstance(state, dict) or not all(
        isinstance(k, str) and isinstance(v, torch.Tensor) for k, v in state.items()
    ):
        raise CheckpointError(
            f"{path}: the checkpoint's 'state_dict' is not a mapping of names to tensors"
        )
    stored_dtype = payload.get("dtype")
    if stored_dtype not in (None, "float32", "float16"):
        raise CheckpointError(
            f"{path}: stored weight dtype {stored_dtype!r} is not float32 or float16"
        )
    if _digest(payload["state_dict"]) != payload["digest"]:
        raise CheckpointError(f"{path}: weights are corrupt (SHA-256 digest mismatch)")
    return payload


def _config_diff(a: dict, b: dict) -> str:
    keys = sorted(set(a) | set(b))
    diffs = [f"{k}: {a.get(k)!r} != {b.get(k)!r}" for k in keys if a.get(k) != b.get(k)]
    return "; ".join(diffs)


def load_model(
    path: str | Path,
    device: str | torch.device = "cpu",
    expect: ModelConfig | None = None,
) -> tuple[torch.nn.Module, ModelConfig, dict[str, Any]]:
    """Load a checkpoint -> (model in eval mode, float32, on ``device``; its ModelConfig; meta).

    ``expect``: the architecture the caller needs; any difference is a CheckpointError.
    """
    path = Path(path)
    payload = read_checkpoint(path, device="cpu")
    try:
        cfg = ModelConfig.model_validate(payload["model_config"])
    except ValidationError as exc:
        raise CheckpointError(
            f"{path}: invalid model config in checkpoint ({exc.errors()[0]['msg']})"
        ) from None
    if expect is not None:
        want, have = expect.model_dump(mode="json"), cfg.model_dump(mode="json")
        want.pop("preset"), have.pop("preset")  # a label, not the architecture
        if want != have:
            raise CheckpointError(
                f"{path}: checkpoint model does not match the requested config "
                f"({_config_diff(want, have)}; checkpoint value on the right)"
            )
    model = build_model(cfg)
    stored = payload["state_dict"]
    state = {k: (v.float() if v.is_floating_point() else v) for k, v in stored.items()}
    try:
        model.load_state_dict(state, strict=True)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()
        detail = _first_sentence(RuntimeError(" ".join(s.strip() for s in first[:2])), 200)
        raise CheckpointError(f"{path}: weights do not fit the stored config ({detail})") from None
    model.to(device, memory_format=torch.channels_last).eval()
    meta = dict(payload.get("meta") or {})
    meta["train_config"] = payload.get("train_config")
    meta["stored_dtype"] = payload.get("dtype")
    meta["weights_digest"] = payload["digest"]  # identifies the weights (databases record it)
    return model, cfg, meta
