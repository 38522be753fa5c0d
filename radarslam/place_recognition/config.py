"""Configuration of the place-recognition data side: accumulation, DPR, image, split, re-ranking.

Every number of the AutoPlace protocol lives here (defaults = the paper / reference code values,
see docs/place_recognition.md). YAML presets are in ``radarslam/configs/place_recognition/``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

from pydantic import Field, field_validator, model_validator

from radarslam.config import StrictModel, load_config
from radarslam.types import RADAR_CHANNELS, check_radar_channel

#: The three radars the reference code filters with DPR (the two side-front radars are never
#: filtered there). Offered as an option; the default filters all five.
REFERENCE_DPR_CHANNELS: tuple[str, ...] = ("RADAR_FRONT", "RADAR_BACK_LEFT", "RADAR_BACK_RIGHT")


def _check_channels(channels: list[str]) -> list[str]:
    bad = [c for c in channels if c not in RADAR_CHANNELS]
    if bad:
        raise ValueError(f"unknown radar channel(s) {bad}; expected a subset of {RADAR_CHANNELS}")
    if len(set(channels)) != len(channels):
        raise ValueError(f"duplicate radar channel in {channels}")
    return channels


def check_device_name(device: str) -> str:
    """A torch device name this code accepts: ``auto`` (CUDA when available), cpu, cuda, cuda:N."""
    if device != "auto" and not (
        device in ("cpu", "cuda") or (device.startswith("cuda:") and device[5:].isdigit())
    ):
        raise ValueError(f"device must be auto, cpu, cuda or cuda:N, got {device!r}")
    return device


class AccumulationConfig(StrictModel):
    """How one key frame's cloud is assembled (devkit ``from_file_multisweep`` semantics)."""

    nsweeps: int = Field(7, ge=1, le=30)
    channels: list[str] = Field(default_factory=lambda: list(RADAR_CHANNELS))
    ref_channel: str = "RADAR_FRONT"  # the image is centred on this sensor at the key frame
    min_distance_m: float = Field(1.0, ge=0.0)  # devkit remove_close(1.0), per sweep

    _v_channels = field_validator("channels")(_check_channels)

    _v_ref = field_validator("ref_channel")(check_radar_channel)


class DPRConfig(StrictModel):
    """Dynamic Points Removal (paper Algorithm 1) on top of the shared Doppler estimator."""

    enabled: bool = True
    # Default: every radar (the paper). The reference code filters only REFERENCE_DPR_CHANNELS.
    channels: list[str] = Field(default_factory=lambda: list(RADAR_CHANNELS))
    static_speed_mps: float = Field(1.0, gt=0.0)  # v_r^tau: "ego static" speed threshold
    static_fraction: float = Field(0.5, ge=0.0, le=1.0)  # p^tau: fraction of slow points
    relative_threshold: float = Field(0.15, gt=0.0)  # RANSAC inlier band = tau * |v_s|
    # Absolute floor of the inlier band (m/s). The paper uses a purely relative band (0.0);
    # a small floor stops a near-zero speed estimate from rejecting everything.
    inlier_threshold_mps: float = Field(0.0, ge=0.0)
    iterations: int = Field(10, ge=1, le=10_000)  # reference: 10 RANSAC iterations
    # The static-ego rule looks at one radar: a side radar of a MOVING car sees its broadside
    # static points at |v_r| < 1 m/s and can trip it, which would then keep only those points.
    # When set, a tripped rule is cross-checked by plain RANSAC: a speed >= static_speed_mps that
    # explains at least as many points means the sensor moves (departure from Algorithm 1).
    verify_static_ego: bool = True
    seed: int = 12345
    # A sweep on which no consistent ego velocity is found: the reference drops it entirely.
    drop_sweep_on_failure: bool = True

    _v_channels = field_validator("channels")(_check_channels)

    @classmethod
    def reference_three_radars(cls, **kw) -> DPRConfig:
        """The reference code's behaviour: DPR only on FRONT, BACK_LEFT, BACK_RIGHT."""
        return cls(channels=list(REFERENCE_DPR_CHANNELS), **kw)


class ImageConfig(StrictModel):
    """The BEV "radar image": rows = x (forward), cols = y (left), centred on the ref sensor."""

    size_px: int = Field(200, ge=8, le=2048)
    resolution_m: float = Field(1.0, gt=0.0)  # metres per pixel
    crop_m: float = Field(100.0, gt=0.0)  # |x|, |y| beyond this are dropped (MEASURE_RANGE)
    # Channel 0 is always binary occupancy; these are appended in order.
    extra_channels: list[Literal["count", "rcs"]] = Field(default_factory=list)
    count_saturation: int = Field(8, ge=1, le=255)  # count channel = min(n, sat) / sat

    @field_validator("extra_channels")
    @classmethod
    def _unique(cls, v: list[str]) -> list[str]:
        if len(set(v)) != len(v):
            raise ValueError(f"duplicate extra channel in {v}")
        return v

    @property
    def num_channels(self) -> int:
        return 1 + len(self.extra_channels)


class SplitConfig(StrictModel):
    """The AutoPlace dataset protocol (the split of the AutoPlace reference code)."""

    # "day": frames from ``split_day`` days after the earliest frame on are held out.
    # "fraction": the last ceil(heldout_day_fraction * n_days) distinct capture days are held out.
    time_split: Literal["day", "fraction"] = "day"
    split_day: float = 105.0
    heldout_day_fraction: float = Field(0.25, gt=0.0, lt=1.0)
    db_spacing_m: float = Field(1.0, ge=0.0)  # greedy DB: add if nearest DB frame > this
    pos_radius_m: float = Field(9.0, gt=0.0)  # positives / evaluation ground truth / query filter
    neg_radius_m: float = Field(18.0, gt=0.0)  # training negatives beyond this
    val_fraction: float = Field(0.2, gt=0.0, lt=1.0)  # val:test = 1:4
    seed: int = 12345
    seq_len: int = Field(3, ge=1, le=16)  # past key frames t-L+1 .. t
    edge_exclusion: int = Field(2, ge=0)  # key frames dropped at each scene end (AVA_SEQ_LEN//2)

    @model_validator(mode="after")
    def _radii(self) -> SplitConfig:
        if self.neg_radius_m < self.pos_radius_m:
            raise ValueError(
                f"neg_radius_m ({self.neg_radius_m}) must be >= pos_radius_m ({self.pos_radius_m})"
            )
        if self.edge_exclusion < self.seq_len - 1:
            raise ValueError(
                f"edge_exclusion ({self.edge_exclusion}) must be >= seq_len - 1 "
                f"({self.seq_len - 1}) so that past frames exist inside the scene"
            )
        return self


class SourceConfig(StrictModel):
    """Which scenes feed the prepared set."""

    dataroot: str | None = None  # nuScenes-layout root (real or synthetic)
    versions: list[str] = Field(default_factory=lambda: ["v1.0-trainval", "v1.0-test"])
    location: str | None = "boston-seaport"  # None: every location
    max_scenes: int | None = Field(None, ge=1)  # cap for quick runs (first scenes in time order)


class PrepareConfig(StrictModel):
    """Everything ``prepare`` needs; its resolved YAML is written into the cache directory."""

    name: str = "autoplace"
    source: SourceConfig = Field(default_factory=SourceConfig)
    accumulation: AccumulationConfig = Field(default_factory=AccumulationConfig)
    dpr: DPRConfig = Field(default_factory=DPRConfig)
    image: ImageConfig = Field(default_factory=ImageConfig)
    split: SplitConfig = Field(default_factory=SplitConfig)

    @field_validator("name")
    @classmethod
    def _name(cls, v: str) -> str:
        if not v or any(ch in v for ch in "/\\ \t\n") or v in {".", ".."}:
            raise ValueError(f"name {v!r} must be a non-empty single path component")
        return v


class RerankConfig(StrictModel):
    """RCS Histogram Re-ranking (paper defaults: M = 100, b_m = 0.02, b_w = 0.04, alpha = 0.41)."""

    enabled: bool = True
    top_m: int = Field(100, ge=1)
    bin_min: float = Field(0.02, ge=0.0, lt=1.0)  # b_m: first bin edge
    bin_width: float = Field(0.04, gt=0.0, lt=1.0)  # b_w
    alpha: float = Field(0.41, ge=0.0, le=1.0)  # weight of KL vs descriptor distance
    epsilon: float = Field(1e-5, gt=0.0)  # added to every histogram count

    @model_validator(mode="after")
    def _bins(self) -> RerankConfig:
        if self.bin_min + self.bin_width >= 1.0:
            raise ValueError(
                f"bin_min + bin_width ({self.bin_min} + {self.bin_width}) must be < 1 "
                "(at least one histogram bin)"
            )
        return self


class RetrievalConfig(StrictModel):
    backend: Literal["auto", "numpy", "faiss"] = "auto"
    faiss_min_database: int = Field(50_000, ge=1)  # "auto" switches to faiss from this size
    chunk_size: int = Field(1024, ge=1)  # queries per numpy distance block


class EvalConfig(StrictModel):
    recall_at: list[int] = Field(default_factory=lambda: [1, 5, 10])
    pr_decimals: int = Field(2, ge=0, le=8)  # thresholds = unique(round(top-1 score, decimals))
    retrieval: RetrievalConfig = Field(default_factory=RetrievalConfig)
    rerank: RerankConfig = Field(default_factory=RerankConfig)
    batch_size: int = Field(32, ge=1)

    @field_validator("recall_at")
    @classmethod
    def _ns(cls, v: list[int]) -> list[int]:
        if not v or any(n < 1 for n in v):
            raise ValueError(f"recall_at must be positive integers, got {v}")
        return sorted(set(v))


class ScanContextConfig(StrictModel):
    """ScanContext (Kim & Kim 2018) for 2-D radar points, in metres (not normalised units)."""

    num_rings: int = Field(20, ge=1)
    num_sectors: int = Field(60, ge=2)
    max_range_m: float = Field(80.0, gt=0.0)
    # Cell value: "count" = log1p(points in the cell) (radar has no height; the paper's max-z
    # collapses to occupancy), "occupancy" = 0/1, "rcs" = max normalised RCS + 1 in occupied cells.
    cell_value: Literal["count", "occupancy", "rcs"] = "count"
    num_candidates: int = Field(50, ge=1)  # ring-key nearest neighbours re-ranked by column shift


class M2DPConfig(StrictModel):
    """M2DP (He et al. 2016): p azimuths x q elevations, l rings x t sectors -> 192-D."""

    num_azimuths: int = Field(4, ge=1)  # p
    num_elevations: int = Field(16, ge=1)  # q
    num_rings: int = Field(8, ge=1)  # l
    num_sectors: int = Field(16, ge=1)  # t


class PlaceRecognizerConfig(StrictModel):
    """The standalone loop detector."""

    accumulation: AccumulationConfig = Field(default_factory=AccumulationConfig)
    dpr: DPRConfig = Field(default_factory=DPRConfig)
    image: ImageConfig = Field(default_factory=ImageConfig)
    rerank: RerankConfig = Field(default_factory=RerankConfig)
    retrieval: RetrievalConfig = Field(default_factory=RetrievalConfig)
    seq_len: int | None = Field(None, ge=1)  # None: the model's own sequence length
    device: str = "cpu"  # "auto" (cuda if available, else cpu), "cpu", "cuda", "cuda:N"

    _v_device = field_validator("device")(check_device_name)


def load_prepare_config(path: str | Path | None, overrides: list[str] | None = None):
    return load_config(PrepareConfig, path, overrides)


def load_eval_config(path: str | Path | None, overrides: list[str] | None = None):
    return load_config(EvalConfig, path, overrides)
