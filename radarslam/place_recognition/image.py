"""BEV "radar image" rasterisation and compact storage.

Pixel of a point (x, y) in the reference-sensor frame, with s = size_px / 2 and r = resolution_m:
``row = floor(x / r + 0.5) + s``, ``col = floor(y / r + 0.5) + s`` (round half up; the reference
uses numpy rounding). A point is kept when ``|x| <= crop_m``, ``|y| <= crop_m`` and both indices
fall in ``[0, size_px)``: with the defaults x in [-100, 99.5) m. Rows = x (forward points down the
image), cols = y (left), exactly as the reference.
"""

from __future__ import annotations

import numpy as np

from radarslam.errors import DataError
from radarslam.place_recognition.config import ImageConfig


def normalise_rcs(rcs: np.ndarray) -> np.ndarray:
    """Per-frame min-max normalisation of RCS (dBsm) to [0, 1]; a constant frame maps to 0."""
    rcs = np.asarray(rcs, dtype=np.float64)
    if rcs.size == 0:
        return rcs.astype(np.float32)
    lo, hi = float(rcs.min()), float(rcs.max())
    if not np.isfinite(lo) or not np.isfinite(hi):
        raise DataError("RCS values contain NaN or infinity")
    if hi - lo <= 0:
        return np.zeros(rcs.shape, dtype=np.float32)
    return ((rcs - lo) / (hi - lo)).astype(np.float32)


def pixel_indices(xy: np.ndarray, cfg: ImageConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(rows, cols, keep): integer pixel of every point and the mask of points inside the image."""
    xy = np.asarray(xy, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[1] < 2:
        raise DataError(f"points must be an (N, 2) array, got shape {xy.shape}")
    if xy.size and not np.all(np.isfinite(xy[:, :2])):
        raise DataError("point coordinates contain NaN or infinity")
    half = cfg.size_px // 2
    rows = np.floor(xy[:, 0] / cfg.resolution_m + 0.5).astype(np.int64) + half
    cols = np.floor(xy[:, 1] / cfg.resolution_m + 0.5).astype(np.int64) + half
    keep = (
        (np.abs(xy[:, 0]) <= cfg.crop_m)
        & (np.abs(xy[:, 1]) <= cfg.crop_m)
        & (rows >= 0)
        & (rows < cfg.size_px)
        & (cols >= 0)
        & (cols < cfg.size_px)
    )
    return rows, cols, keep


def crop_mask(xy: np.ndarray, cfg: ImageConfig) -> np.ndarray:
    """Points that land in the image (the same set feeds the image, RCS vector and baselines)."""
    return pixel_indices(xy, cfg)[2]


def rasterise(xy: np.ndarray, cfg: ImageConfig, rcs01: np.ndarray | None = None) -> np.ndarray:
    """(C, H, W) uint8 image. Channel 0: occupancy {0, 1}; extra channels quantised to 0..255.

    ``rcs01`` (per point, already in [0, 1]) is needed only for an ``rcs`` extra channel, which
    holds the maximum normalised RCS per pixel.
    """
    rows, cols, keep = pixel_indices(xy, cfg)
    rows, cols = rows[keep], cols[keep]
    size = cfg.size_px
    out = np.zeros((cfg.num_channels, size, size), dtype=np.uint8)
    flat = rows * size + cols
    out[0].flat[flat] = 1
    for c, kind in enumerate(cfg.extra_channels, start=1):
        if kind == "count":
            counts = np.bincount(flat, minlength=size * size)
            sat = cfg.count_saturation
            q = np.rint(np.minimum(counts, sat) * (255.0 / sat)).astype(np.uint8)
            out[c] = q.reshape(size, size)
        else:  # rcs
            if rcs01 is None:
                raise DataError("an 'rcs' image channel needs per-point RCS values")
            vals = np.asarray(rcs01, dtype=np.float64)
            if len(vals) != len(keep):
                raise DataError(f"{len(vals)} RCS values for {len(keep)} points")
            best = np.zeros(size * size)
            np.maximum.at(best, flat, np.clip(vals[keep], 0.0, 1.0))
            q = np.rint(best * 255.0).astype(np.uint8)
            q[out[0].ravel() == 0] = 0
            out[c] = q.reshape(size, size)
    return out


def pack_images(images: np.ndarray) -> np.ndarray:
    """Bit-pack binary occupancy images (N, H, W) along the last axis (8x smaller)."""
    images = np.asarray(images)
    if images.size and images.max() > 1:
        raise DataError("pack_images expects binary {0, 1} images")
    return np.packbits(images.astype(np.uint8), axis=-1)


def unpack_images(packed: np.ndarray, width: int) -> np.ndarray:
    return np.unpackbits(packed, axis=-1, count=width)
