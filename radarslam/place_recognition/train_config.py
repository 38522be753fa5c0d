"""Settings of an AutoPlace training run, and what a run returns."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

from pydantic import Field, model_validator

from radarslam.config import CONFIG_DIR, StrictModel, load_config
from radarslam.errors import ConfigError

from .config import check_device_name

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
    #: Start every layer from this checkpoint, a model of the same architecture: fine-tuning
    #: trained weights (the shipped ones, say) on new data. Ignored when resuming.
    init_weights_from: str | None = None
    #: Also train every query that has positives driven the other way round: its images turned
    #: by 180 deg (what SLAM's turned search, ``loops.reversed_search``, queries) against those
    #: positives, mined as the others. Validation then also measures the turned queries, and the
    #: best epoch is selected on R@1 pooled over both kinds of query.
    turned_queries: bool = False
    #: A positive is driven the other way round when its heading lies this close to the query's
    #: turned by 180 deg.
    turned_max_heading_error_deg: float = Field(45.0, gt=0, le=90)

    @model_validator(mode="after")
    def _check(self) -> TrainConfig:
        if self.init_encoder_from and self.init_weights_from:
            raise ValueError(
                "init_encoder_from and init_weights_from are exclusive (the second sets every "
                "layer, the encoder included)"
            )
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


@dataclass
class TrainResult:
    best_checkpoint: Path
    last_checkpoint: Path
    history: list[dict] = field(default_factory=list)
    best_epoch: int = 0
    #: val R@1 of the best epoch (pooled with the turned queries under ``turned_queries``)
    best_recall_at_1: float = float("nan")
