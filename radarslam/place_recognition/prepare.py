"""Preprocessing: key-frame index, radar images + RCS + points, and the split, cached on disk.

``prepare(cfg, out_root)`` writes ``out_root/<cfg.name>/`` (hloc style: the resolved config is
written there as ``config.yaml``) with one file per stage:

- ``frames.npz``  key frames (positions, yaw, timestamps, scene names, sample tokens, versions)
- ``images.npz``  bit-packed occupancy images (+ optional extra channels), ``points.npz`` the
  cropped points (int16 centimetres) and their min-max-normalised RCS (float16), ``dpr.json``
- ``split.npz`` / ``split.json``  database/train/val/test indices and the (N, L) sequences.

Each stage stores a hash of the config sections it depends on. A stage whose files all exist and
are readable is skipped; if its hash differs from the current config, ``ConfigError`` unless
``overwrite=True``. A stage that is recomputed (missing, damaged or overwritten) first deletes its
files and those of every later stage, and ``config.yaml`` is written last: an interrupted or failed
run never leaves files of two configs that :func:`~.dataset.load_prepared` would
trust (it checks every file's hash against ``config.yaml``).
"""

from __future__ import annotations

import itertools
import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from radarslam.config import dump_config
from radarslam.errors import ConfigError, DataError
from radarslam.geometry import yaw_of
from radarslam.io.atomic import atomic_open, write_json_atomic, write_text_atomic
from radarslam.place_recognition.config import PrepareConfig
from radarslam.place_recognition.dataset import (
    CONFIG_FILE,
    DPR_FILE,
    FRAMES_FILE,
    IMAGES_FILE,
    NPZ_ERRORS,
    POINTS_FILE,
    SPLIT_FILE,
    SPLIT_JSON,
    SPLIT_NAMES,
    STAGE_FILES,
    STAGE_SECTIONS,
    STAGES,
    make_split,
    stage_hash,
)
from radarslam.place_recognition.image import crop_mask, normalise_rcs, pack_images, rasterise
from radarslam.place_recognition.outputs import check_output_dir

log = logging.getLogger("radarslam.place_recognition")

#: Arrays each .npz must hold to count as written.
_NPZ_ARRAYS = {
    FRAMES_FILE: ("positions_xy", "yaw_rad", "timestamps_us", "scene_names", "sample_tokens",
                  "versions"),
    POINTS_FILE: ("xy_cm", "rcs01", "offsets"),
    IMAGES_FILE: ("occupancy_packed", "extra", "width"),
    SPLIT_FILE: ("sequences", *SPLIT_NAMES),
}  # fmt: skip


def _save_npz(path: Path, **arrays) -> None:
    with atomic_open(path, "wb") as fh:
        np.savez_compressed(fh, **arrays)


def _stored_hash(path: Path) -> str | None:
    """The config hash of a stage .npz; None when it is missing, damaged (a truncated zip...) or
    lacks an array: such a stage is recomputed."""
    try:
        with path.open("rb") as fh:
            if not fh.read(4).startswith(b"PK"):
                return None
        with np.load(path, allow_pickle=False) as z:
            want = ("config_hash", *_NPZ_ARRAYS.get(path.name, ()))
            if any(k not in z.files for k in want):
                return None
            return str(z["config_hash"])
    except NPZ_ERRORS:
        return None


def _json_ok(path: Path) -> bool:
    try:
        return isinstance(json.loads(path.read_text(encoding="utf-8")), dict)
    except (OSError, ValueError):  # ValueError: bad JSON or bad UTF-8
        return False


def _remove_stage_files(out: Path, stages: list[str]) -> None:
    """Delete the files (and stray temporaries) of ``stages`` before they are recomputed."""
    for stage in stages:
        for name in STAGE_FILES[stage]:
            (out / name).unlink(missing_ok=True)
            for tmp in out.glob(f".{name}.*.tmp"):
                tmp.unlink(missing_ok=True)


@dataclass(frozen=True)
class KeyFrameIndex:
    positions_xy: np.ndarray
    yaw_rad: np.ndarray
    timestamps_us: np.ndarray
    scene_names: np.ndarray
    sample_tokens: np.ndarray
    versions: np.ndarray


def _readers(cfg: PrepareConfig):
    from radarslam.nuscenes.reader import NuScenesRadar

    src = cfg.source
    if not src.dataroot:
        raise ConfigError("source.dataroot is not set (give --dataroot or set it in the config)")
    root = Path(src.dataroot)
    if not root.is_dir():
        raise DataError(f"{root}: dataroot does not exist")
    readers = {}
    for version in src.versions:
        if not (root / version).is_dir():
            raise DataError(f"{root / version}: nuScenes version directory does not exist")
        readers[version] = NuScenesRadar(root, version)
    return readers


def _selected_scenes(cfg: PrepareConfig, readers) -> list[tuple[int, str, object]]:
    """(start time, version, SceneInfo) of the wanted scenes, in time order."""
    out = []
    for version, reader in readers.items():
        if cfg.source.location is not None:
            if cfg.source.location not in reader.locations():
                continue
            scenes = reader.scenes_for_location(cfg.source.location)
        else:
            scenes = reader.scenes()
        out += [(reader.scene_start_us(s), version, s) for s in scenes]
    if not out:
        raise DataError(
            f"{cfg.source.dataroot}: no scene at location {cfg.source.location!r} "
            f"in {cfg.source.versions}"
        )
    out.sort(key=lambda t: (t[0], t[2].name))
    if cfg.source.max_scenes is not None:
        out = out[: cfg.source.max_scenes]
    return out


def build_index(cfg: PrepareConfig, readers, progress: bool = True) -> KeyFrameIndex:
    """Key frames (samples with a reference-channel key-frame sweep), scenes in time order."""
    from tqdm import tqdm

    ref = cfg.accumulation.ref_channel
    rows = []
    scenes = _selected_scenes(cfg, readers)
    for _, version, scene in tqdm(scenes, desc="index", unit="scene", disable=not progress):
        for frame in readers[version].iter_frames(scene, key_frames_only=True, ref_channel=ref):
            if ref not in frame.sweeps:
                continue  # the image is centred on the reference sensor: no sweep, no frame
            pose = frame.world_from_ego
            rows.append((pose[0, 3], pose[1, 3], yaw_of(pose), frame.timestamp_us, scene.name,
                         frame.sample_token, version))  # fmt: skip
    if not rows:
        raise DataError(f"{cfg.source.dataroot}: the selected scenes have no {ref} key frame")
    cols = list(zip(*rows, strict=True))
    return KeyFrameIndex(
        positions_xy=np.column_stack([cols[0], cols[1]]).astype(np.float64),
        yaw_rad=np.asarray(cols[2], np.float64),
        timestamps_us=np.asarray(cols[3], np.int64),
        scene_names=np.asarray(cols[4], dtype=str),
        sample_tokens=np.asarray(cols[5], dtype=str),
        versions=np.asarray(cols[6], dtype=str),
    )


@dataclass(frozen=True)
class FrameCloud:
    """What one key frame contributes: its cropped points, normalised RCS and image."""

    xy: np.ndarray  # (P, 2) float64, reference-sensor frame, inside the image
    rcs01: np.ndarray  # (P,) float32 in [0, 1]
    image: np.ndarray  # (C, H, W) uint8


def frame_from_cloud(cloud, cfg: PrepareConfig | None = None, image_cfg=None) -> FrameCloud:
    """Crop, normalise RCS and rasterise an :class:`AccumulatedCloud` (or (xy, rcs_dbsm))."""
    image_cfg = image_cfg or (cfg.image if cfg is not None else None)
    if image_cfg is None:
        raise ConfigError("frame_from_cloud needs an image config")
    if isinstance(cloud, tuple):
        xy, rcs = cloud
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        rcs = np.asarray(rcs, dtype=np.float64).reshape(-1)
    else:
        xy = np.column_stack([cloud.points["x"], cloud.points["y"]]).astype(np.float64)
        rcs = cloud.points["rcs"].astype(np.float64)
    if len(rcs) != len(xy):
        raise DataError(f"{len(rcs)} RCS values for {len(xy)} points")
    keep = crop_mask(xy, image_cfg)
    xy, rcs01 = xy[keep], normalise_rcs(rcs[keep])
    return FrameCloud(xy=xy, rcs01=rcs01, image=rasterise(xy, image_cfg, rcs01))


def _clouds_for(cfg: PrepareConfig, readers, tokens, versions, progress: bool = False):
    """Images, points and DPR stats of a list of key frames (one process)."""
    from tqdm import tqdm

    from radarslam.place_recognition.dpr import DPRStats, DynamicPointsRemoval

    acc = cfg.accumulation
    dpr = DynamicPointsRemoval(cfg.dpr) if cfg.dpr.enabled else None
    n = len(tokens)
    size = cfg.image.size_px
    occ = np.zeros((n, size, (size + 7) // 8), np.uint8)
    extra = np.zeros((n, cfg.image.num_channels - 1, size, size), np.uint8)
    xy_parts, rcs_parts = [], []
    counts = np.zeros(n, np.int64)
    for i in tqdm(range(n), desc="clouds", unit="frame", disable=not progress):
        cloud = readers[str(versions[i])].accumulate(
            str(tokens[i]),
            nsweeps=acc.nsweeps,
            channels=acc.channels,
            ref_channel=acc.ref_channel,
            min_distance_m=acc.min_distance_m,
            point_mask=dpr,
        )
        fc = frame_from_cloud(cloud, image_cfg=cfg.image)
        occ[i] = pack_images(fc.image[0])
        if len(extra[i]):
            extra[i] = fc.image[1:]
        xy_parts.append(np.clip(np.rint(fc.xy * 100.0), -32767, 32767).astype(np.int16))
        rcs_parts.append(fc.rcs01.astype(np.float16))
        counts[i] = len(fc.xy)
    xy_cm = np.concatenate(xy_parts) if xy_parts else np.zeros((0, 2), np.int16)
    rcs01 = np.concatenate(rcs_parts) if rcs_parts else np.zeros(0, np.float16)
    return occ, extra, xy_cm, rcs01, counts, dpr.stats if dpr is not None else DPRStats()


def _clouds_worker(job):
    cfg_json, tokens, versions = job
    cfg = PrepareConfig.model_validate_json(cfg_json)
    return _clouds_for(cfg, _readers(cfg), tokens, versions)


def build_clouds(
    cfg: PrepareConfig, readers, index: KeyFrameIndex, progress: bool = True, jobs: int = 1
):
    """Accumulate (with DPR) every key frame; returns images, points, rcs, offsets, DPR stats.

    ``jobs > 1`` splits the frames into contiguous chunks processed by worker processes (each opens
    its own readers); the result is identical to ``jobs = 1``.
    """
    n = len(index.sample_tokens)
    if jobs <= 1 or n < 2 * jobs:
        parts = [_clouds_for(cfg, readers, index.sample_tokens, index.versions, progress)]
    else:
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        from tqdm import tqdm

        bounds = np.linspace(0, n, min(n, 4 * jobs) + 1).astype(int)
        chunks = [
            (cfg.model_dump_json(), index.sample_tokens[a:b].tolist(), index.versions[a:b].tolist())
            for a, b in itertools.pairwise(bounds)
        ]
        parts = []
        with (
            ProcessPoolExecutor(jobs, mp_context=mp.get_context("spawn")) as pool,
            tqdm(total=n, desc="clouds", unit="frame", disable=not progress) as bar,
        ):
            for part in pool.map(_clouds_worker, chunks):
                parts.append(part)
                bar.update(len(part[4]))
    occ = np.concatenate([p[0] for p in parts])
    extra = np.concatenate([p[1] for p in parts])
    xy_cm = np.concatenate([p[2] for p in parts])
    rcs01 = np.concatenate([p[3] for p in parts])
    offsets = np.concatenate([[0], np.cumsum(np.concatenate([p[4] for p in parts]))])
    if cfg.dpr.enabled:
        total = parts[0][5]
        for p in parts[1:]:
            total.merge(p[5])
        stats = total.as_dict()
    else:
        stats = {"enabled": False}
    return occ, extra, xy_cm, rcs01, offsets.astype(np.int64), stats


def _check_cache(out: Path, cfg: PrepareConfig, overwrite: bool) -> list[str]:
    """Stages to (re)compute; raises on a stale stage when not overwriting.

    Every file of a stage is checked: a missing or damaged one makes the stage recompute.
    """
    check_output_dir(out)
    todo = []
    stale = False
    for stage in STAGES:
        want = stage_hash(cfg, stage)
        complete = True
        for name in STAGE_FILES[stage]:
            path = out / name
            if name.endswith(".json"):
                complete = complete and path.is_file() and _json_ok(path)
                continue
            have = _stored_hash(path) if path.is_file() else None
            if have is not None and have != want and not overwrite:
                raise ConfigError(
                    f"{path} was made with a different config "
                    f"({', '.join(STAGE_SECTIONS[stage])}); "
                    "pass overwrite=True (--overwrite) or use another name"
                )
            complete = complete and have == want
        if stale or not complete or overwrite:
            todo.append(stage)
            stale = True  # later stages depend on earlier ones
    return todo


def prepare(
    cfg: PrepareConfig,
    out_root: str | Path,
    overwrite: bool = False,
    progress: bool = True,
    readers=None,
    on_stage: Callable[[str], None] | None = None,
    jobs: int = 1,
) -> Path:
    """Run the missing stages into ``out_root/<cfg.name>``; returns that directory.

    ``jobs``: worker processes for the accumulation stage (the expensive one).
    """
    if jobs < 1:
        raise ConfigError(f"jobs={jobs}: must be >= 1")
    check_output_dir(out_root)
    out = Path(out_root) / cfg.name
    todo = _check_cache(out, cfg, overwrite)
    if not todo:
        log.info("%s: every stage is cached", out)
        write_text_atomic(out / CONFIG_FILE, dump_config(cfg))
        return out
    if readers is None and ("frames" in todo or "clouds" in todo):
        readers = _readers(cfg)
    # The stages to recompute (always a stage and every later one) lose their old files first,
    # so a failure below leaves missing files, never files of another config; the directory
    # itself is created by the first write.
    _remove_stage_files(out, todo)

    if "frames" in todo:
        if on_stage:
            on_stage("frames")
        idx = build_index(cfg, readers, progress)
        _save_npz(out / FRAMES_FILE, config_hash=stage_hash(cfg, "frames"),
                  positions_xy=idx.positions_xy, yaw_rad=idx.yaw_rad,
                  timestamps_us=idx.timestamps_us, scene_names=idx.scene_names,
                  sample_tokens=idx.sample_tokens, versions=idx.versions)  # fmt: skip
    with np.load(out / FRAMES_FILE, allow_pickle=False) as z:
        idx = KeyFrameIndex(**{k: z[k] for k in KeyFrameIndex.__dataclass_fields__})
    # The split needs only the key frames' poses and times: one that cannot be made (a single
    # capture day, say) fails now, not after the clouds' accumulation.
    split = (
        make_split(idx.positions_xy, idx.timestamps_us, idx.scene_names, cfg.split)
        if "split" in todo
        else None
    )

    if "clouds" in todo:
        if on_stage:
            on_stage("clouds")
        occ, extra, xy_cm, rcs01, offsets, stats = build_clouds(cfg, readers, idx, progress, jobs)
        _save_npz(out / POINTS_FILE, config_hash=stage_hash(cfg, "clouds"), xy_cm=xy_cm,
                  rcs01=rcs01, offsets=offsets)  # fmt: skip
        write_json_atomic(out / DPR_FILE, stats)
        # images last: their hash marks the stage complete
        _save_npz(out / IMAGES_FILE, config_hash=stage_hash(cfg, "clouds"),
                  occupancy_packed=occ, extra=extra, width=np.int64(cfg.image.size_px))  # fmt: skip

    if split is not None:
        if on_stage:
            on_stage("split")
        _save_npz(out / SPLIT_FILE, config_hash=stage_hash(cfg, "split"),
                  sequences=split.sequences, **split.splits)  # fmt: skip
        write_json_atomic(out / SPLIT_JSON, split.counts)
    # last: the resolved config describes the directory only once every stage matches it
    write_text_atomic(out / CONFIG_FILE, dump_config(cfg))
    return out
