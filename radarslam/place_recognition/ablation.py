"""The paper's ablation (Table II): SE, SE+TE, SE+DPR, SE+TE+DPR, each with and without RCSHR.

Two prepared caches share one split (it depends on poses only): ``<name>`` with DPR and
``<name>_nodpr`` without. Each variant's network is trained with :func:`.train.train`
unless a checkpoint for it is found in ``checkpoint_dir`` (``<size>_<slug>.pt`` or
``<size>/<slug>.pt`` or ``<size>_<slug>/best.pt``, slug in se, se_te, se_dpr, se_te_dpr). RCSHR
parameters are tuned per variant on the validation split only, then applied to test.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from radarslam.errors import CheckpointError
from radarslam.place_recognition.config import EvalConfig, PrepareConfig
from radarslam.place_recognition.dataset import PreparedData, load_prepared
from radarslam.place_recognition.evaluate import (
    EvalResult,
    descriptor_ranking_fn,
    evaluate_method,
    model_describe_fn,
)

log = logging.getLogger("radarslam.place_recognition")


@dataclass(frozen=True)
class Variant:
    name: str  # paper row label
    slug: str
    temporal: bool
    dpr: bool


VARIANTS: tuple[Variant, ...] = (
    Variant("SE", "se", False, False),
    Variant("SE+TE", "se_te", True, False),
    Variant("SE+DPR", "se_dpr", False, True),
    Variant("SE+TE+DPR", "se_te_dpr", True, True),
)


def prepare_pair(
    cfg: PrepareConfig,
    cache_root: str | Path,
    overwrite: bool = False,
    progress: bool = True,
    jobs: int = 1,
) -> tuple[Path, Path]:
    """(with-DPR cache, without-DPR cache) of one data config."""
    from radarslam.place_recognition.prepare import prepare

    with_dpr = cfg.model_copy(update={"dpr": cfg.dpr.model_copy(update={"enabled": True})})
    no_dpr = cfg.model_copy(
        update={"name": f"{cfg.name}_nodpr", "dpr": cfg.dpr.model_copy(update={"enabled": False})}
    )
    return (
        prepare(with_dpr, cache_root, overwrite=overwrite, progress=progress, jobs=jobs),
        prepare(no_dpr, cache_root, overwrite=overwrite, progress=progress, jobs=jobs),
    )


def find_checkpoint(checkpoint_dir: str | Path | None, size: str, slug: str) -> Path | None:
    if checkpoint_dir is None:
        return None
    d = Path(checkpoint_dir)
    names = (f"{size}_{slug}.pt", f"{size}/{slug}.pt", f"{size}_{slug}/best.pt")
    for cand in (d / n for n in names):
        if cand.is_file():
            return cand
    return None


@dataclass
class VariantRun:
    variant: Variant
    checkpoint: Path
    trained: bool
    parameters: int
    results: list[EvalResult]


def run_variant(
    variant: Variant,
    data: PreparedData,
    size: str,
    model_presets: dict[str, str],
    train_preset: str,
    out_dir: str | Path,
    eval_cfg: EvalConfig,
    checkpoint_dir: str | Path | None = None,
    train_overrides: list[str] | None = None,
    allow_train: bool = True,
    tune_rcshr: bool = True,
    device: str = "cpu",
    progress: bool = True,
) -> VariantRun:
    """Train (or load) one variant's network and evaluate it on test, with and without RCSHR."""
    from radarslam.place_recognition.checkpoint import load_model
    from radarslam.place_recognition.models import load_model_config, parameter_count

    preset = model_presets["se_te" if variant.temporal else "se"]
    ckpt = find_checkpoint(checkpoint_dir, size, variant.slug)
    trained = False
    if ckpt is None:
        if not allow_train:
            raise CheckpointError(
                f"no checkpoint for {size} {variant.name} in {checkpoint_dir} "
                f"(expected {size}_{variant.slug}.pt)"
            )
        from radarslam.place_recognition.train import load_train_config, train

        model_cfg = load_model_config(preset)
        train_cfg = load_train_config(train_preset, train_overrides)
        result = train(train_cfg, model_cfg, data, Path(out_dir) / f"{size}_{variant.slug}",
                       progress=progress)  # fmt: skip
        ckpt, trained = Path(result.best_checkpoint), True
    model, model_cfg, _ = load_model(ckpt, device=device)
    if model_cfg.seq_len > data.seq_len:
        raise CheckpointError(f"{ckpt}: needs {model_cfg.seq_len} frames, data has {data.seq_len}")
    describe = model_describe_fn(model, data, eval_cfg.batch_size, device)
    fn = descriptor_ranking_fn(data, describe, eval_cfg)
    results = evaluate_method(data, variant.name, fn, eval_cfg, "test", rerank_cfg=eval_cfg.rerank,
                              tune_on_val=tune_rcshr)  # fmt: skip
    return VariantRun(variant, ckpt, trained, parameter_count(model), results)


def run_ablation(
    data_dpr: PreparedData,
    data_nodpr: PreparedData,
    out_dir: str | Path,
    size: str = "compact",
    model_presets: dict[str, str] | None = None,
    train_preset: str = "compact_cpu",
    eval_cfg: EvalConfig | None = None,
    checkpoint_dir: str | Path | None = None,
    train_overrides: list[str] | None = None,
    allow_train: bool = True,
    tune_rcshr: bool = True,
    device: str = "cpu",
    variants: tuple[Variant, ...] = VARIANTS,
    progress: bool = True,
    on_variant: Callable[[VariantRun], None] | None = None,
    te_init_from_se: bool = False,
) -> list[VariantRun]:
    """All variants; returns their runs (rows ordered as the paper's Table II).

    ``te_init_from_se``: a TE variant that is trained here starts its encoder from the SE variant
    with the same DPR setting (two-stage training; that SE variant must come first in
    ``variants`` or have a checkpoint).
    """
    for k in ("database", "train", "val", "test"):
        if not np.array_equal(data_dpr.splits[k], data_nodpr.splits[k]):
            raise CheckpointError(
                f"{data_dpr.root} and {data_nodpr.root} have different '{k}' splits; "
                "prepare both from the same config"
            )
    presets = model_presets or {"se": f"{size}_se", "se_te": f"{size}_se_te"}
    eval_cfg = eval_cfg or EvalConfig()
    runs = []
    checkpoints: dict[str, Path] = {}
    for v in variants:
        overrides = list(train_overrides or [])
        if te_init_from_se and v.temporal:
            se_slug = "se_dpr" if v.dpr else "se"
            se_ckpt = checkpoints.get(se_slug) or find_checkpoint(checkpoint_dir, size, se_slug)
            if se_ckpt is None:
                raise CheckpointError(
                    f"{size} {v.name}: two-stage training needs the {size} {se_slug} checkpoint "
                    "first (run that variant before it)"
                )
            overrides.append(f"init_encoder_from={se_ckpt}")
        run = run_variant(v, data_dpr if v.dpr else data_nodpr, size, presets, train_preset,
                          out_dir, eval_cfg, checkpoint_dir, overrides, allow_train,
                          tune_rcshr, device, progress)  # fmt: skip
        checkpoints[v.slug] = run.checkpoint
        runs.append(run)
        if on_variant:
            on_variant(run)
    return runs


def table_ii_rows(runs: list[VariantRun]) -> list[dict]:
    """Rows in the paper's order: the four variants, full AutoPlace, then the other RCSHR rows."""
    by_name = {r.name: r for run in runs for r in run.results}
    order = ["SE", "SE+TE", "SE+DPR", "SE+TE+DPR", "SE+TE+DPR+RCSHR", "SE+RCSHR",
             "SE+DPR+RCSHR", "SE+TE+RCSHR"]  # fmt: skip
    params = {r.name: run.parameters for run in runs for r in run.results}
    rows = []
    for name in order:
        if name in by_name:
            row = by_name[name].row()
            row["params"] = params[name]
            rows.append(row)
    return rows


def load_pair(cfg: PrepareConfig, cache_root: str | Path) -> tuple[PreparedData, PreparedData]:
    a, b = prepare_pair(cfg, cache_root)
    return load_prepared(a), load_prepared(b)
