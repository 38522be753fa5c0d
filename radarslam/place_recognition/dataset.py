"""The AutoPlace dataset protocol, the prepared cache's files (written by :mod:`.prepare`) and
the prepared-data container.

Split rules (those of the AutoPlace reference code's split and its refinement), all pure
functions of per-frame positions, timestamps and scene membership:

1. Frames are ordered by scene (scenes in time order) then key-frame order; the first and last
   ``edge_exclusion`` key frames of every scene belong to no set (past frames must exist).
2. Time split: frames from a given day on (or the last fraction of capture days) are held out.
3. Database: greedy over the remaining pool in frame order; a frame joins when its nearest DB frame
   is more than ``db_spacing_m`` away. Training queries are the other pool frames.
4. Every query (train / held-out) is kept only if a DB frame lies within ``pos_radius_m``.
5. Held-out queries are split val:test = val_fraction : 1 - val_fraction with a seeded permutation.
Positives are DB frames within ``pos_radius_m`` (distance <= radius, sklearn ``radius_neighbors``
semantics); training negatives are DB frames farther than ``neg_radius_m``.
"""

from __future__ import annotations

import hashlib
import json
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from radarslam.errors import ConfigError, DataError
from radarslam.place_recognition.config import PrepareConfig, SplitConfig

DAY_US = 86_400 * 1_000_000
SPLIT_NAMES = ("database", "train", "val", "test")

FRAMES_FILE = "frames.npz"
IMAGES_FILE = "images.npz"
POINTS_FILE = "points.npz"
SPLIT_FILE = "split.npz"
CONFIG_FILE = "config.yaml"
DPR_FILE = "dpr.json"
SPLIT_JSON = "split.json"

STAGES = ("frames", "clouds", "split")
#: The config sections each stage of a prepared cache depends on.
STAGE_SECTIONS = {
    "frames": ("source", "accumulation"),
    "clouds": ("source", "accumulation", "dpr", "image"),
    "split": ("source", "accumulation", "split"),
}
#: Every file of a stage, in writing order (the last one marks the stage complete).
STAGE_FILES = {
    "frames": (FRAMES_FILE,),
    "clouds": (POINTS_FILE, DPR_FILE, IMAGES_FILE),
    "split": (SPLIT_FILE, SPLIT_JSON),
}


def stage_hash(cfg: PrepareConfig, stage: str) -> str:
    """Hash of the config sections ``stage`` depends on, stored in each of its files."""
    data = cfg.model_dump(mode="json")
    part = {k: data[k] for k in STAGE_SECTIONS[stage]}
    return hashlib.sha1(json.dumps(part, sort_keys=True).encode()).hexdigest()[:16]


# ----------------------------------------------------------------------------------------------
# split logic
# ----------------------------------------------------------------------------------------------
def _check_positions(positions_xy: np.ndarray) -> np.ndarray:
    p = np.asarray(positions_xy, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 2:
        raise DataError(f"positions must be (N, 2), got shape {p.shape}")
    if not np.all(np.isfinite(p)):
        raise DataError("positions contain NaN or infinity")
    return p


def scene_starts(scene_names: np.ndarray) -> np.ndarray:
    """Index of the first frame of each frame's scene; scenes must be contiguous blocks."""
    names = np.asarray(scene_names)
    n = len(names)
    if n == 0:
        return np.zeros(0, np.int64)
    new = np.ones(n, bool)
    new[1:] = names[1:] != names[:-1]
    firsts = np.flatnonzero(new)
    if len(set(names[firsts].tolist())) != len(firsts):
        raise DataError("frames of one scene are not contiguous (frames must be sorted by scene)")
    return firsts[np.cumsum(new) - 1]


def scene_positions(scene_names: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(position of each frame inside its scene, length of its scene)."""
    starts = scene_starts(scene_names)
    pos = np.arange(len(starts)) - starts
    _, inverse, counts = np.unique(starts, return_inverse=True, return_counts=True)
    return pos, counts[inverse].astype(np.int64)


def build_sequences(scene_names: np.ndarray, seq_len: int) -> np.ndarray:
    """(N, L) frame indices t-L+1 .. t (oldest first), clamped at the start of the scene."""
    starts = scene_starts(scene_names)
    t = np.arange(len(starts))
    offsets = np.arange(-(seq_len - 1), 1)
    return np.maximum(t[:, None] + offsets[None, :], starts[:, None]).astype(np.int64)


def edge_mask(scene_names: np.ndarray, edge: int) -> np.ndarray:
    """True for frames at least ``edge`` key frames away from both ends of their scene."""
    pos, length = scene_positions(scene_names)
    return (pos >= edge) & (pos < length - edge)


def heldout_mask(timestamps_us: np.ndarray, cfg: SplitConfig) -> np.ndarray:
    """True for frames in the held-out (val + test) time period."""
    t = np.asarray(timestamps_us, dtype=np.int64)
    if len(t) == 0:
        return np.zeros(0, bool)
    if cfg.time_split == "day":
        days = (t - t.min()) // DAY_US
        return days >= cfg.split_day
    day = t // DAY_US  # capture (UTC) day of each frame
    uniq = np.unique(day)
    n_out = int(np.ceil(cfg.heldout_day_fraction * len(uniq)))
    if n_out >= len(uniq):
        raise DataError(
            f"only {len(uniq)} capture day(s): heldout_day_fraction={cfg.heldout_day_fraction} "
            "would hold out every day"
        )
    return day >= uniq[len(uniq) - n_out]


def greedy_database(
    positions_xy: np.ndarray, candidates: np.ndarray, spacing_m: float
) -> np.ndarray:
    """Frames (in ``candidates`` order) kept by the greedy rule: nearest DB frame > spacing_m."""
    p = _check_positions(positions_xy)
    cell = max(spacing_m, 1e-6)
    grid: dict[tuple[int, int], list[int]] = {}
    chosen: list[int] = []
    for i in np.asarray(candidates, dtype=np.int64):
        x, y = p[i]
        cx, cy = int(np.floor(x / cell)), int(np.floor(y / cell))
        too_close = False
        for dx in (-1, 0, 1):
            for dy in (-1, 0, 1):
                for j in grid.get((cx + dx, cy + dy), ()):
                    if (p[j, 0] - x) ** 2 + (p[j, 1] - y) ** 2 <= spacing_m * spacing_m:
                        too_close = True
                        break
                if too_close:
                    break
            if too_close:
                break
        if not too_close:
            grid.setdefault((cx, cy), []).append(int(i))
            chosen.append(int(i))
    return np.asarray(chosen, dtype=np.int64)


def has_neighbour(
    positions_xy: np.ndarray, queries: np.ndarray, database: np.ndarray, radius_m: float
) -> np.ndarray:
    """Bool per query: some DB frame lies within ``radius_m`` (inclusive)."""
    from scipy.spatial import cKDTree

    p = _check_positions(positions_xy)
    queries = np.asarray(queries, dtype=np.int64)
    if len(database) == 0 or len(queries) == 0:
        return np.zeros(len(queries), bool)
    d, _ = cKDTree(p[database]).query(p[queries], k=1)
    return d <= radius_m


@dataclass(frozen=True)
class Split:
    splits: dict[str, np.ndarray]
    sequences: np.ndarray
    counts: dict[str, int]


def make_split(
    positions_xy: np.ndarray,
    timestamps_us: np.ndarray,
    scene_names: np.ndarray,
    cfg: SplitConfig,
) -> Split:
    """The full AutoPlace protocol on frames sorted by scene then time."""
    p = _check_positions(positions_xy)
    t = np.asarray(timestamps_us, dtype=np.int64)
    names = np.asarray(scene_names)
    if not (len(p) == len(t) == len(names)):
        raise DataError(f"{len(p)} positions, {len(t)} timestamps, {len(names)} scene names")
    usable = edge_mask(names, cfg.edge_exclusion)
    held = heldout_mask(t, cfg)
    pool = np.flatnonzero(usable & ~held)
    heldout = np.flatnonzero(usable & held)
    if len(pool) == 0:
        raise DataError("no frame left for the database/training pool (check the time split)")
    if len(heldout) == 0:
        raise DataError("no held-out frame for val/test (check the time split)")
    database = greedy_database(p, pool, cfg.db_spacing_m)
    in_db = np.zeros(len(p), bool)
    in_db[database] = True
    train = pool[~in_db[pool]]
    train_kept = train[has_neighbour(p, train, database, cfg.pos_radius_m)]
    held_kept = heldout[has_neighbour(p, heldout, database, cfg.pos_radius_m)]
    rng = np.random.default_rng(cfg.seed)
    perm = rng.permutation(len(held_kept))
    n_val = int(np.rint(cfg.val_fraction * len(held_kept)))
    val = np.sort(held_kept[perm[:n_val]])
    test = np.sort(held_kept[perm[n_val:]])
    splits = {"database": database, "train": train_kept, "val": val, "test": test}
    counts = {k: len(v) for k, v in splits.items()}
    counts.update(
        frames=len(p),
        edge_excluded=int((~usable).sum()),
        pool=len(pool),
        heldout=len(heldout),
        train_dropped=len(train) - len(train_kept),
        heldout_dropped=len(heldout) - len(held_kept),
    )
    return Split(splits=splits, sequences=build_sequences(names, cfg.seq_len), counts=counts)


# ----------------------------------------------------------------------------------------------
# prepared data
# ----------------------------------------------------------------------------------------------
@dataclass
class PreparedData:
    """A prepared cache directory loaded in memory (see ``radarslam.place_recognition.prepare``)."""

    root: Path
    # (N, H, W) uint8 {0, 1}; with extra channels (N, C, H, W) float16 in [0, 1]
    images: np.ndarray
    positions_xy: np.ndarray  # (N, 2) world x, y of the RADAR_FRONT key-frame ego pose
    yaw_rad: np.ndarray  # (N,)
    timestamps_us: np.ndarray  # (N,) int64
    scene_names: np.ndarray  # (N,) str
    sample_tokens: np.ndarray  # (N,) str
    rcs: list[np.ndarray]  # per frame, RCS min-max normalised to [0, 1]
    sequences: np.ndarray  # (N, L) frame indices, oldest first, inside one scene
    splits: dict[str, np.ndarray]  # "database", "train", "val", "test" -> frame indices
    pos_radius_m: float = 9.0
    neg_radius_m: float = 18.0
    points_xy: list[np.ndarray] = field(default_factory=list)  # per frame (P, 2) float32, ref frame
    config: PrepareConfig | None = None
    _db_tree: object = field(default=None, repr=False)

    def __len__(self) -> int:
        return len(self.positions_xy)

    @classmethod
    def from_drives(
        cls,
        root: str | Path,
        images: np.ndarray,
        positions_xy: np.ndarray,
        drive_names: np.ndarray,
        seq_len: int = 3,
        frame_interval_us: int = 500_000,
    ) -> PreparedData:
        """In-memory data of synthetic drives (heading 0, no RCS) whose names are their split:
        ``db`` is the database, ``train`` / ``val`` / ``test`` the queries, each from its
        ``seq_len``-th frame on (a query needs its past frames)."""
        names = np.asarray(drive_names)
        n = len(names)
        splits = {"database": np.flatnonzero(names == "db")}
        for split in ("train", "val", "test"):
            splits[split] = np.flatnonzero(names == split)[seq_len - 1 :]
        return cls(
            root=Path(root),
            images=np.stack(images),
            positions_xy=np.asarray(positions_xy, dtype=float),
            yaw_rad=np.zeros(n),
            timestamps_us=np.arange(n, dtype=np.int64) * frame_interval_us,
            scene_names=names,
            sample_tokens=np.array([f"token{i}" for i in range(n)]),
            rcs=[np.zeros(0, np.float32)] * n,
            sequences=build_sequences(names, seq_len),
            splits=splits,
        )

    @property
    def num_channels(self) -> int:
        return 1 if self.images.ndim == 3 else self.images.shape[1]

    @property
    def seq_len(self) -> int:
        return self.sequences.shape[1]

    def frames_float(self, indices: np.ndarray, seq_len: int | None = None) -> np.ndarray:
        """(M, L, C, H, W) float32 in [0, 1]: the last ``seq_len`` frames of each sequence."""
        seq = self.sequences[np.asarray(indices, dtype=np.int64)]
        if seq_len is not None:
            if seq_len > seq.shape[1]:
                raise ConfigError(f"seq_len {seq_len} > prepared sequence length {seq.shape[1]}")
            seq = seq[:, seq.shape[1] - seq_len :]
        imgs = self.images[seq]  # (M, L, H, W) or (M, L, C, H, W)
        if self.images.ndim == 3:
            imgs = imgs[:, :, None]
        return imgs.astype(np.float32)

    def _tree(self):
        if self._db_tree is None:
            from scipy.spatial import cKDTree

            self._db_tree = cKDTree(self.positions_xy[self.splits["database"]])
        return self._db_tree

    def positives(self, query_idx: int) -> np.ndarray:
        """DB frame indices within ``pos_radius_m`` of the query frame (sorted)."""
        db = self.splits["database"]
        hits = self._tree().query_ball_point(self.positions_xy[int(query_idx)], self.pos_radius_m)
        return np.sort(db[np.asarray(hits, dtype=np.int64)])

    def reversed_positives(self, query_idx: int, max_heading_error_deg: float) -> np.ndarray:
        """Positives driven the other way round: heading within ``max_heading_error_deg`` of the
        query's turned by 180 deg. What the query's turned images
        (:func:`~.descriptors.turn_images`) should retrieve."""
        q = int(query_idx)
        pos = self.positives(q)
        off = np.angle(np.exp(1j * (self.yaw_rad[pos] - self.yaw_rad[q] - np.pi)))
        return pos[np.abs(off) <= np.deg2rad(max_heading_error_deg)]

    def negatives_pool(self, query_idx: int) -> np.ndarray:
        """DB frame indices farther than ``neg_radius_m`` from the query frame."""
        db = self.splits["database"]
        d = np.linalg.norm(self.positions_xy[db] - self.positions_xy[int(query_idx)], axis=1)
        return db[d > self.neg_radius_m]

    def is_positive(self, query_idx: np.ndarray, db_frames: np.ndarray) -> np.ndarray:
        """Broadcast: whether frame ``db_frames[..]`` lies within the positive radius of a query."""
        q = self.positions_xy[np.asarray(query_idx, dtype=np.int64)]
        d = self.positions_xy[np.asarray(db_frames, dtype=np.int64)]
        while q.ndim < d.ndim:
            q = q[:, None, :]
        return np.linalg.norm(d - q, axis=-1) <= self.pos_radius_m


NPZ_ERRORS = (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error)
"""What reading a damaged .npz raises (a truncated zip, a bad CRC, a broken deflate stream...)."""

STALE_HINT = "re-run `radarslam pr prepare --overwrite`"
REDO_HINT = "re-run `radarslam pr prepare` (it recomputes damaged stages)"


def read_npz(path: str | Path) -> dict[str, np.ndarray]:
    """Every array of an .npz (no pickles); ValueError with a short reason when the file is not
    a readable .npz (empty, another format, truncated, a bad CRC or deflate stream...)."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            head = fh.read(4)
        if not head:
            raise ValueError("empty file")
        if not head.startswith(b"PK"):
            raise ValueError("not an .npz (zip) archive")
        with np.load(path, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except NPZ_ERRORS as exc:
        if isinstance(exc, OSError) and exc.strerror:
            text = exc.strerror
        else:
            text = " ".join(str(exc).split())[:160] or type(exc).__name__
        if isinstance(exc, zipfile.BadZipFile | zlib.error | EOFError):
            text = f"damaged or truncated archive: {text}"
        raise ValueError(text) from None


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    if not path.is_file():
        raise DataError(f"{path}: missing (run `radarslam pr prepare` first)")
    try:
        return read_npz(path)
    except ValueError as exc:
        raise DataError(f"{path}: unreadable ({exc}); {REDO_HINT}") from None


def _need(d: dict, keys: tuple[str, ...], path: Path) -> None:
    missing = [k for k in keys if k not in d]
    if missing:
        raise DataError(f"{path}: missing array(s) {missing}")


def split_offsets(values: np.ndarray, offsets: np.ndarray) -> list[np.ndarray]:
    return [values[offsets[i] : offsets[i + 1]] for i in range(len(offsets) - 1)]


def load_prepared(root: str | Path, with_points: bool = True) -> PreparedData:
    """Load a prepared cache directory written by :func:`.prepare.prepare`.

    ``with_points=False`` skips ``points.npz`` (RCS and points: only RCSHR and the handcrafted
    baselines need them), e.g. to train from a copy that lacks it.
    """
    from radarslam.config import build_config, read_yaml
    from radarslam.place_recognition.image import unpack_images

    root = Path(root)
    if not root.is_dir():
        raise DataError(f"{root}: prepared directory does not exist")
    cfg = build_config(PrepareConfig, read_yaml(root / CONFIG_FILE), str(root / CONFIG_FILE))
    frames = _load_npz(root / FRAMES_FILE)
    _need(frames, ("positions_xy", "yaw_rad", "timestamps_us", "scene_names", "sample_tokens"),
          root / FRAMES_FILE)  # fmt: skip
    images = _load_npz(root / IMAGES_FILE)
    _need(images, ("occupancy_packed", "width"), root / IMAGES_FILE)
    if with_points:
        points = _load_npz(root / POINTS_FILE)
        _need(points, ("xy_cm", "rcs01", "offsets"), root / POINTS_FILE)
    else:
        points = {"xy_cm": np.zeros((0, 2), np.int16), "rcs01": np.zeros(0, np.float32)}
    split = _load_npz(root / SPLIT_FILE)
    _need(split, ("sequences", *SPLIT_NAMES), root / SPLIT_FILE)

    _check_stages(root, cfg, {FRAMES_FILE: frames, IMAGES_FILE: images, SPLIT_FILE: split,
                              **({POINTS_FILE: points} if with_points else {})})  # fmt: skip
    n = _check_frames(frames, root / FRAMES_FILE)
    _check_split(split, n, root / SPLIT_FILE)
    width, packed = images["width"], images["occupancy_packed"]
    if width.size != 1 or not np.issubdtype(width.dtype, np.integer) or packed.ndim != 3:
        raise DataError(f"{root / IMAGES_FILE}: malformed images (width {width}, packed shape "
                        f"{packed.shape}); {STALE_HINT}")  # fmt: skip
    occ = unpack_images(packed, int(width))
    if len(occ) != n:
        raise DataError(f"{root / IMAGES_FILE}: {len(occ)} images for {n} frames; {STALE_HINT}")
    if "extra" in images and images["extra"].size:
        shape = images["extra"].shape
        if len(shape) != 4 or shape[0] != n or shape[2:] != occ.shape[1:]:
            raise DataError(
                f"{root / IMAGES_FILE}: extra channels {images['extra'].shape} do not match "
                f"{n} images of {occ.shape[1:]}; {STALE_HINT}"
            )
        # extra channels are stored quantised 0..255; in memory every channel is in [0, 1]
        extra = images["extra"].astype(np.float16) / np.float16(255.0)
        imgs = np.concatenate([occ[:, None].astype(np.float16), extra], axis=1)
    else:
        imgs = occ
    if with_points:
        offsets = points["offsets"].astype(np.int64)
        if (
            offsets.ndim != 1
            or len(offsets) != n + 1
            or offsets[0] != 0
            or np.any(np.diff(offsets) < 0)
            or offsets[-1] != len(points["rcs01"])
            or len(points["xy_cm"]) != len(points["rcs01"])
        ):
            raise DataError(f"{root / POINTS_FILE}: offsets do not match {n} frames; {STALE_HINT}")
    xy = points["xy_cm"].astype(np.float32) / 100.0
    return PreparedData(
        root=root,
        images=imgs,
        positions_xy=frames["positions_xy"].astype(np.float64),
        yaw_rad=frames["yaw_rad"].astype(np.float64),
        timestamps_us=frames["timestamps_us"].astype(np.int64),
        scene_names=frames["scene_names"].astype(str),
        sample_tokens=frames["sample_tokens"].astype(str),
        rcs=split_offsets(points["rcs01"].astype(np.float32), offsets) if with_points else [],
        sequences=split["sequences"].astype(np.int64),
        splits={k: split[k].astype(np.int64) for k in SPLIT_NAMES},
        pos_radius_m=cfg.split.pos_radius_m,
        neg_radius_m=cfg.split.neg_radius_m,
        points_xy=split_offsets(xy, offsets) if with_points else [],
        config=cfg,
    )


def _check_stages(root: Path, cfg: PrepareConfig, files: dict[str, dict]) -> None:
    """Every stage file must carry the hash of ``config.yaml``'s sections for its stage: a file
    left over from another config (an interrupted or failed ``prepare --overwrite``) is stale."""
    for stage, names in STAGE_FILES.items():
        want = stage_hash(cfg, stage)
        for name in names:
            arrays = files.get(name)
            if arrays is None or "config_hash" not in arrays:
                continue  # not loaded, or written by hand without a hash
            if str(arrays["config_hash"]) != want:
                raise DataError(
                    f"{root / name}: stale stage (made with another config than "
                    f"{root / CONFIG_FILE}); {STALE_HINT}"
                )


def _check_frames(frames: dict, path: Path) -> int:
    pos = frames["positions_xy"]
    if pos.ndim != 2 or pos.shape[1:] != (2,):
        raise DataError(f"{path}: positions_xy must be (N, 2), got {pos.shape}; {STALE_HINT}")
    n = len(pos)
    for key in ("yaw_rad", "timestamps_us", "scene_names", "sample_tokens"):
        if frames[key].shape != (n,):
            raise DataError(
                f"{path}: {key} has shape {frames[key].shape}, expected ({n},); {STALE_HINT}"
            )
    return n


def _check_split(split: dict, n: int, path: Path) -> None:
    seq = split["sequences"]
    if seq.ndim != 2 or len(seq) != n or seq.shape[1] < 1:
        raise DataError(f"{path}: sequences are {seq.shape}, expected ({n}, L); {STALE_HINT}")
    for key in ("sequences", *SPLIT_NAMES):
        idx = split[key]
        if idx.size and not np.issubdtype(idx.dtype, np.integer):
            raise DataError(f"{path}: '{key}' holds {idx.dtype}, not frame indices; {STALE_HINT}")
        if key != "sequences" and idx.ndim != 1:
            raise DataError(f"{path}: '{key}' must be 1-D, got {idx.shape}; {STALE_HINT}")
        if idx.size and (idx.min() < 0 or idx.max() >= n):
            raise DataError(
                f"{path}: '{key}' indexes frames outside [0, {n}) (stale stage); {STALE_HINT}"
            )


def split_summary(root: str | Path) -> dict:
    """The split counts written by ``prepare`` (``split.json``)."""
    path = Path(root) / SPLIT_JSON
    if not path.is_file():
        raise DataError(f"{path}: missing; {REDO_HINT}")
    try:
        counts = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:  # ValueError: JSON and UTF-8 decoding errors
        text = " ".join(str(exc).split())[:120]
        raise DataError(f"{path}: unreadable ({text}); {REDO_HINT}") from None
    if not isinstance(counts, dict):
        raise DataError(f"{path}: expected a JSON object of split counts; {REDO_HINT}")
    return counts
