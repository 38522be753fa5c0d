"""AutoPlace networks: the spatial encoder (SE) and the temporal encoder (TE).

Re-implemented from the paper and the documented behaviour of its reference code, not from
the reference code itself:

- SE: VGG-like blocks of 3x3 convolutions (stride 1, padding 1, bias) each followed by ReLU, a 2x2
  max-pool after every block, no BatchNorm/dropout; then an L2 normalisation of the channel vector
  at every spatial position, one extra 2x2 max-pool, flatten, and L2 over the whole vector. With the
  paper widths (64-128-256-256) and a 200x200 input this is 256x6x6 = 9216-D.
- TE: each frame of the sequence (t-L+1 .. t, oldest first) goes through the SE trunk; the pooled
  map is L2-normalised per position again, flattened, and fed to a one-layer unidirectional LSTM
  (zero initial state). The last time step's output, L2-normalised, is the descriptor. For
  inference the LSTM splits into a per-frame input projection (``frame_codes``, cached by the
  recognizer: a frame enters ``seq_len`` sequences) and the recurrence (``aggregate_codes``).

The input normalisation lives inside the model so that callers pass raw occupancy in [0, 1]:
the reference replicated the binary image into 3 channels and applied the ImageNet mean/std, and
so does this model (``input_norm="imagenet"``), which keeps the first convolution's parameter
count and gradient dynamics identical to the reference.

torch is imported at module level here: this module is only imported by the training / inference
code paths, never by the CLI at start-up.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import torch
import torch.nn.functional as F
from pydantic import Field, model_validator
from torch import nn

from radarslam.config import CONFIG_DIR, StrictModel, load_config
from radarslam.errors import ConfigError

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)

PRESETS = ("paper_se", "paper_se_te", "compact_se", "compact_se_te")


class ModelConfig(StrictModel):
    """Architecture of one AutoPlace network (SE alone, or SE+TE)."""

    preset: str = "compact_se_te"
    image_size_px: int = Field(200, ge=8)  # square BEV image side (1 m/px in AutoPlace)
    in_channels: int = Field(1, ge=1)  # channels per frame in the data (binary occupancy: 1)
    widths: list[int] = Field(default_factory=lambda: [16, 32, 64, 64], min_length=1)
    convs_per_block: int = Field(2, ge=1)
    seq_len: int = Field(3, ge=1)  # frames per sequence: (t-L+1 .. t)
    use_temporal: bool = True  # TE on (LSTM over the sequence) / off (SE of frame t only)
    # TE: the LSTM hidden size (= descriptor size). SE: derived from widths and image size; a value
    # given here must match it (so a YAML file states the descriptor size it expects).
    descriptor_dim: int | None = Field(None, ge=1)
    input_norm: Literal["imagenet", "none"] = "imagenet"

    @model_validator(mode="after")
    def _check(self) -> ModelConfig:
        if any(w < 1 for w in self.widths):
            raise ValueError(f"widths must be positive, got {self.widths}")
        if self.pooled_size_px() < 1:
            raise ValueError(
                f"image_size_px={self.image_size_px} is too small for {len(self.widths)} blocks "
                "plus the extra 2x2 pool (the pooled map would be empty)"
            )
        if self.input_norm == "imagenet" and self.in_channels not in (1, 3):
            raise ValueError(
                f"input_norm='imagenet' needs in_channels 1 (replicated to 3) or 3, "
                f"got {self.in_channels}"
            )
        if not self.use_temporal:
            if self.seq_len != 1:
                raise ValueError(f"SE (use_temporal=false) uses one frame; seq_len={self.seq_len}")
            if self.descriptor_dim is not None and self.descriptor_dim != self.frame_feature_dim():
                raise ValueError(
                    f"SE descriptor_dim={self.descriptor_dim} does not match widths/image size, "
                    f"which give {self.frame_feature_dim()}"
                )
        elif self.descriptor_dim is None:
            raise ValueError("TE (use_temporal=true) needs descriptor_dim (the LSTM hidden size)")
        return self

    def pooled_size_px(self) -> int:
        """Side of the final feature map: one floor-halving per block, plus the extra pool."""
        side = self.image_size_px
        for _ in range(len(self.widths) + 1):
            side //= 2
        return side

    def frame_feature_dim(self) -> int:
        """Length of one frame's flattened SE feature (9216 for the paper at 200x200)."""
        return self.widths[-1] * self.pooled_size_px() ** 2

    def output_dim(self) -> int:
        """Length of the final descriptor."""
        return self.descriptor_dim if self.use_temporal else self.frame_feature_dim()

    def net_in_channels(self) -> int:
        return 3 if self.input_norm == "imagenet" else self.in_channels


def load_model_config(name_or_path: str | Path, overrides: list[str] | None = None) -> ModelConfig:
    """A preset name (``compact_se_te``) or a YAML path -> ModelConfig."""
    path = Path(name_or_path)
    if not path.suffix:
        path = CONFIG_DIR / "place_recognition" / f"model_{name_or_path}.yaml"
        if not path.is_file():
            raise ConfigError(
                f"unknown model preset {str(name_or_path)!r} (known: {', '.join(PRESETS)})"
            )
    return load_config(ModelConfig, path, overrides)


class AutoPlaceNet(nn.Module):
    """SE or SE+TE. ``forward(x)`` takes (B, L, C, H, W) occupancy in [0, 1] -> (B, D), unit L2.

    For training with many shared frames, ``forward(frames, seq_index)`` takes the unique frames
    (U, C, H, W) plus a (B, L) long tensor of indices into them, so each frame is encoded once
    (and the call still goes through ``forward``, which DistributedDataParallel requires).
    """

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        layers: list[nn.Module] = []
        cin = cfg.net_in_channels()
        for width in cfg.widths:
            for _ in range(cfg.convs_per_block):
                layers += [nn.Conv2d(cin, width, 3, stride=1, padding=1), nn.ReLU(inplace=True)]
                cin = width
            layers.append(nn.MaxPool2d(2, 2))
        self.encoder = nn.Sequential(*layers)
        self.pool = nn.MaxPool2d(2, 2)
        if cfg.input_norm == "imagenet":
            mean = torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1)
            std = torch.tensor(IMAGENET_STD).view(1, 3, 1, 1)
        else:
            mean = torch.zeros(1, cfg.in_channels, 1, 1)
            std = torch.ones(1, cfg.in_channels, 1, 1)
        # Not persistent: they are constants of the config, not learned state.
        self.register_buffer("mean", mean, persistent=False)
        self.register_buffer("std", std, persistent=False)
        self.lstm = (
            nn.LSTM(cfg.frame_feature_dim(), cfg.descriptor_dim, num_layers=1, batch_first=True)
            if cfg.use_temporal
            else None
        )

    def encode_frames(self, frames: torch.Tensor) -> torch.Tensor:
        """(N, C, H, W) occupancy in [0, 1] -> (N, F) per-frame features (pre-aggregation)."""
        cfg = self.cfg
        if frames.ndim != 4 or frames.shape[1:] != (
            cfg.in_channels,
            cfg.image_size_px,
            cfg.image_size_px,
        ):
            raise ValueError(
                f"frames must be (N, {cfg.in_channels}, {cfg.image_size_px}, "
                f"{cfg.image_size_px}), got {tuple(frames.shape)}"
            )
        x = frames.to(self.mean.dtype)
        if cfg.input_norm == "imagenet" and cfg.in_channels == 1:
            x = x.expand(-1, 3, -1, -1)
        x = (x - self.mean) / self.std
        # The convolution weights are channels-last; an NCHW input would be converted before
        # every convolution (measured 3x slower on 2 CPU threads).
        x = self.encoder(x.contiguous(memory_format=torch.channels_last))
        x = F.normalize(x, p=2, dim=1)  # per-position L2 over channels
        x = self.pool(x)
        if self.lstm is not None:
            # TE re-normalises every position of the pooled map before flattening.
            x = F.normalize(x, p=2, dim=1)
        return x.flatten(1)

    def aggregate(self, feats: torch.Tensor) -> torch.Tensor:
        """(B, L, F) per-frame features, oldest first -> (B, D) unit descriptors."""
        if self.lstm is None:
            out = feats[:, -1]
        else:
            out, _ = self.lstm(feats)  # zero initial state
            out = out[:, -1]
        return F.normalize(out, p=2, dim=1)

    def frame_codes(self, feats: torch.Tensor) -> torch.Tensor:
        """(N, F) per-frame features -> (N, K) the part of :meth:`aggregate` that each frame
        contributes on its own: the LSTM's input projection with both biases (K = 4 x hidden,
        gates in torch's i, f, g, o order); SE: the features unchanged. A recognizer caches these
        per frame: a frame enters ``seq_len`` consecutive sequences, and the projection (a
        2304 x 1024 matrix for the compact model) is most of the LSTM's cost."""
        if self.lstm is None:
            return feats
        lstm = self.lstm
        return F.linear(feats, lstm.weight_ih_l0, lstm.bias_ih_l0 + lstm.bias_hh_l0)

    def aggregate_codes(self, codes: torch.Tensor) -> torch.Tensor:
        """(B, L, K) per-frame codes (:meth:`frame_codes`), oldest first -> (B, D) unit
        descriptors; equal to :meth:`aggregate` of the features up to float rounding (the same
        single-layer LSTM recurrence, zero initial state, written out for inference)."""
        if self.lstm is None:
            return F.normalize(codes[:, -1], p=2, dim=1)
        w_hh = self.lstm.weight_hh_l0
        h = codes.new_zeros(codes.shape[0], w_hh.shape[1])
        c = torch.zeros_like(h)
        for t in range(codes.shape[1]):
            i, f, g, o = (codes[:, t] + h @ w_hh.T).chunk(4, dim=1)
            c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
            h = torch.sigmoid(o) * torch.tanh(c)
        return F.normalize(h, p=2, dim=1)

    def forward(self, x: torch.Tensor, seq_index: torch.Tensor | None = None) -> torch.Tensor:
        seq_len = self.cfg.seq_len
        if seq_index is None:
            if x.ndim != 5:
                raise ValueError(f"input must be (B, L, C, H, W), got {tuple(x.shape)}")
            if x.shape[1] < seq_len:
                raise ValueError(f"sequence has {x.shape[1]} frames, the model needs {seq_len}")
            x = x[:, -seq_len:]
            b = x.shape[0]
            feats = self.encode_frames(x.reshape(b * seq_len, *x.shape[2:]))
            return self.aggregate(feats.view(b, seq_len, -1))
        if seq_index.ndim != 2 or seq_index.shape[1] < seq_len:
            raise ValueError(f"seq_index must be (B, >={seq_len}), got {tuple(seq_index.shape)}")
        feats = self.encode_frames(x)
        return self.aggregate(feats[seq_index[:, -seq_len:]])


def build_model(cfg: ModelConfig) -> AutoPlaceNet:
    """A freshly initialised network (PyTorch default initialisation, as the reference).

    Convolution weights are channels_last (NHWC): oneDNN then runs the whole trunk in NHWC, which
    measured 1.4x (paper) to 3.1x (compact) more frames/s on 2 CPU threads than NCHW; inputs may
    stay ordinary contiguous tensors.
    """
    return AutoPlaceNet(cfg).to(memory_format=torch.channels_last)


def parameter_count(model: nn.Module) -> int:
    """Number of learnable scalars (works on meta-device models too)."""
    return sum(p.numel() for p in model.parameters())


def expected_parameter_count(cfg: ModelConfig) -> int:
    """Closed-form parameter count, so the 220 M-parameter paper TE can be checked unallocated.

    conv: cin*cout*9 + cout each; LSTM (PyTorch keeps two bias vectors): 4*(F*H + H*H + 2*H).
    """
    total = 0
    cin = cfg.net_in_channels()
    for width in cfg.widths:
        for _ in range(cfg.convs_per_block):
            total += cin * width * 9 + width
            cin = width
    if cfg.use_temporal:
        f, h = cfg.frame_feature_dim(), cfg.descriptor_dim
        total += 4 * (f * h + h * h + 2 * h)
    return total


def multiply_adds_per_frame(cfg: ModelConfig) -> int:
    """Multiply-adds to encode one frame (convolutions) plus one LSTM step when TE is on.

    A descriptor of a sequence costs ``seq_len`` frames, but in a stream (or a descriptor cache)
    every frame is encoded once and reused by the next sequences, so per-frame cost is what counts.
    """
    side = cfg.image_size_px
    total = 0
    cin = cfg.net_in_channels()
    for width in cfg.widths:
        for _ in range(cfg.convs_per_block):
            total += side * side * cin * width * 9
            cin = width
        side //= 2
    if cfg.use_temporal:
        f, h = cfg.frame_feature_dim(), cfg.descriptor_dim
        total += 4 * (f * h + h * h)
    return total
