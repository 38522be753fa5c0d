"""The standalone loop detector: AutoPlace descriptors + exact search + RCSHR re-ranking.

    rec = PlaceRecognizer()                      # the shipped compact checkpoint
    cloud = rec.cloud_from_reader(reader, sample_token)   # 5 radars x 7 sweeps, DPR applied
    candidates = rec.query([prev2, prev1, cloud], k=5)    # pure: the database is not changed
    rec.add([prev2, prev1, cloud], key=sample_token)      # explicit insertion

Inputs are :class:`~radarslam.types.AccumulatedCloud` objects in the reference-sensor frame (or
:class:`~.prepare.FrameCloud`), alone or as a sequence oldest first; a temporal
model needs ``seq_len`` frames and a shorter sequence is padded by repeating its oldest frame (the
same rule as at a scene start). Dynamic points must be removed while accumulating (the points no
longer carry their sensor's line of sight): :meth:`PlaceRecognizer.cloud_from_reader` does that.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections import OrderedDict
from collections.abc import Callable, Collection, Hashable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from radarslam.config import build_config
from radarslam.errors import CheckpointError, DataError
from radarslam.place_recognition.archive import check_archive
from radarslam.place_recognition.config import PlaceRecognizerConfig
from radarslam.place_recognition.rcshr import bin_edges, kl_divergence, rcs_histogram
from radarslam.place_recognition.retrieval import DescriptorIndex, check_k
from radarslam.types import AccumulatedCloud

DEFAULT_CHECKPOINT = Path(__file__).resolve().parent / "weights" / "compact.pt"


def checkpoint_path(checkpoint: str | Path | None) -> Path:
    """The checkpoint file to load (None: the shipped compact weights); CheckpointError if it
    is not there."""
    path = Path(checkpoint) if checkpoint is not None else DEFAULT_CHECKPOINT
    if not path.exists():
        hint = "" if checkpoint is not None else " (default compact weights not installed)"
        raise CheckpointError(f"{path}: checkpoint not found{hint}")
    check_archive(path)  # a folder, an empty, truncated or foreign file fails here, without torch
    return path


DB_FORMAT = "radarslam.place_db"

#: The point fields a key frame's image and RCS values are made of (``frame_from_cloud``).
_IMAGE_FIELDS = ("x", "y", "rcs")
#: Slack on the [0, 1] range of normalised RCS values (float32 rounding).
_RCS_TOLERANCE = 1e-6


@dataclass(frozen=True)
class PlaceCandidate:
    """One retrieved place."""

    key: Hashable  # what was given to ``add``
    descriptor_distance: float  # Euclidean distance between global descriptors
    score: float  # re-ranked score (alpha * KL + (1 - alpha) * d), = distance without RCSHR
    rank: int  # 0 = best


class PlaceRecognizer:
    """A database of places and the AutoPlace pipeline to describe and query them."""

    def __init__(
        self,
        model=None,
        checkpoint: str | Path | None = None,
        config: PlaceRecognizerConfig | None = None,
    ):
        from radarslam.place_recognition.train import resolve_device

        self.config = config or PlaceRecognizerConfig()
        if model is not None and checkpoint is not None:
            raise CheckpointError("give either a model or a checkpoint, not both")
        # before any weights are read: an unusable device is a one-line ConfigError
        self.device = resolve_device(self.config.device)
        self.checkpoint = None
        #: SHA-256 of the checkpoint's weights (None for a model given in memory)
        self.checkpoint_digest: str | None = None
        if model is None:
            path = checkpoint_path(checkpoint)
            from radarslam.place_recognition.checkpoint import load_model

            model, _, ck_meta = load_model(path, device=self.device)
            self.checkpoint = path
            self.checkpoint_digest = ck_meta.get("weights_digest")
        self.model = model
        if hasattr(model, "eval"):
            model.eval()
        model_cfg = getattr(model, "cfg", None)
        model_seq = getattr(model_cfg, "seq_len", None)
        if self.config.seq_len is not None and model_seq is not None:
            if self.config.seq_len != model_seq:
                raise CheckpointError(
                    f"config seq_len={self.config.seq_len} but the model uses {model_seq} frames"
                )
        self.seq_len = int(self.config.seq_len or model_seq or 1)
        in_ch = getattr(model_cfg, "in_channels", None)
        if in_ch is not None and in_ch != self.config.image.num_channels:
            raise CheckpointError(
                f"model expects {in_ch} image channel(s), config makes "
                f"{self.config.image.num_channels}"
            )
        size = getattr(model_cfg, "image_size_px", None)
        if size is not None and size != self.config.image.size_px:
            raise CheckpointError(
                f"model expects {size} px images, config makes {self.config.image.size_px}"
            )
        #: descriptor length the model makes, checked on the first add (None: unknown)
        self._model_dim = self._model_output_dim()
        self._edges = bin_edges(self.config.rerank.bin_min, self.config.rerank.bin_width)
        self._keys: list[Hashable] = []
        self._key_set: set = set()
        self._hists: list[np.ndarray] = []
        self._rcs: list[np.ndarray] = []
        self._index: DescriptorIndex | None = None
        # Per-frame codes (the CNN features through the LSTM's input projection) of the most
        # recent clouds: in a SLAM loop each key frame enters seq_len consecutive sequences and
        # only its first use needs the CNN and the projection.
        self._feature_cache: OrderedDict[tuple, np.ndarray] = OrderedDict()
        self._cache_size = 4 * self.seq_len
        self._split_model = all(
            hasattr(model, name) for name in ("encode_frames", "frame_codes", "aggregate_codes")
        )

    # ---- inputs ------------------------------------------------------------------------------
    def cloud_from_reader(self, reader, sample_token: str) -> AccumulatedCloud:
        """Accumulate a key frame with this recognizer's sweeps/radars and DPR settings."""
        from radarslam.place_recognition.dpr import make_point_mask

        acc = self.config.accumulation
        return reader.accumulate(
            sample_token,
            nsweeps=acc.nsweeps,
            channels=acc.channels,
            ref_channel=acc.ref_channel,
            min_distance_m=acc.min_distance_m,
            point_mask=make_point_mask(self.config.dpr),
        )

    def _frame(self, item):
        from radarslam.place_recognition.prepare import FrameCloud, frame_from_cloud

        if isinstance(item, FrameCloud):
            return item
        if isinstance(item, AccumulatedCloud):
            want = self.config.accumulation.ref_channel
            if item.ref_channel != want:
                raise DataError(
                    f"cloud {item.sample_token or item.timestamp_us} is in the "
                    f"{item.ref_channel or 'ego'} frame; the images are centred on {want}"
                )
            _check_point_fields(item)
            return frame_from_cloud(item, image_cfg=self.config.image)
        raise DataError(
            f"expected an AccumulatedCloud or FrameCloud (or a sequence of them), "
            f"got {type(item).__name__}"
        )

    def _items(self, frame_or_cloud) -> list:
        items = (
            list(frame_or_cloud) if isinstance(frame_or_cloud, (list, tuple)) else [frame_or_cloud]
        )
        if not items:
            raise DataError("empty frame sequence")
        items = items[-self.seq_len :]
        while len(items) < self.seq_len:
            items.insert(0, items[0])
        return items

    @staticmethod
    def _cache_key(item) -> tuple | None:
        """Feature-cache key of a cloud: its identity and a fingerprint of the point values its
        image is made of, so that points changed in place, or another cloud under the same
        token, never get stale features (about 0.1 ms for a 4000-point key frame)."""
        if isinstance(item, AccumulatedCloud) and item.sample_token:
            fingerprint = _points_fingerprint(item.points)
            if fingerprint is None:
                return None
            return (item.sample_token, item.timestamp_us, item.ref_channel, fingerprint)
        return None

    @staticmethod
    def _image(frame) -> np.ndarray:
        img = frame.image.astype(np.float32)  # (C, H, W)
        if img.shape[0] > 1:
            img[1:] /= 255.0
        return img

    def describe(self, frame_or_cloud) -> tuple[np.ndarray, np.ndarray]:
        """(descriptor (D,) float32, current-frame RCS values in [0, 1]; empty for a key frame
        without points in the image)."""
        items = self._items(frame_or_cloud)
        last = self._frame(items[-1])
        if not self._split_model:
            frames = [self._frame(it) for it in items[:-1]] + [last]
            stack = np.stack([self._image(f) for f in frames])  # (L, C, H, W)
            return self._run_model(stack[None])[0], last.rcs01
        feats = []
        for pos, it in enumerate(items):
            key = self._cache_key(it)
            if key is not None and key in self._feature_cache:
                self._feature_cache.move_to_end(key)
                feats.append(self._feature_cache[key])
                continue
            frame = last if pos == len(items) - 1 else self._frame(it)
            f = self._encode(self._image(frame)[None])[0]
            if key is not None:
                self._feature_cache[key] = f
                while len(self._feature_cache) > self._cache_size:
                    self._feature_cache.popitem(last=False)
            feats.append(f)
        return self._aggregate(np.stack(feats)[None])[0], last.rcs01

    def _encode(self, images: np.ndarray) -> np.ndarray:
        import torch

        with torch.no_grad():
            feats = self.model.encode_frames(torch.from_numpy(images).to(self.device))
            out = self.model.frame_codes(feats)
        return out.detach().float().cpu().numpy()

    def _aggregate(self, codes: np.ndarray) -> np.ndarray:
        import torch

        with torch.no_grad():
            out = self.model.aggregate_codes(torch.from_numpy(codes).to(self.device))
        out = out.detach().float().cpu().numpy()
        if out.ndim != 2 or not np.all(np.isfinite(out)):
            raise CheckpointError(f"model returned {out.shape} (non-finite or wrong shape)")
        return out.astype(np.float32)

    def _run_model(self, batch: np.ndarray) -> np.ndarray:
        import torch

        with torch.no_grad():
            x = torch.from_numpy(batch).to(self.device)
            out = self.model(x)
        out = out.detach().float().cpu().numpy() if hasattr(out, "detach") else np.asarray(out)
        if out.ndim != 2 or len(out) != len(batch) or not np.all(np.isfinite(out)):
            raise CheckpointError(f"model returned {out.shape} (non-finite or wrong shape)")
        return out.astype(np.float32)

    # ---- database ----------------------------------------------------------------------------
    def __len__(self) -> int:
        return len(self._keys)

    @property
    def keys(self) -> list[Hashable]:
        return list(self._keys)

    def add(self, frame_or_cloud, key: Hashable) -> None:
        """Describe and insert one place under ``key`` (unique, JSON-serialisable for ``save``)."""
        desc, rcs = self.describe(frame_or_cloud)
        self.add_descriptor(desc, rcs, key)

    def add_descriptor(self, descriptor: np.ndarray, rcs01: np.ndarray, key: Hashable) -> None:
        """Insert a place described by :meth:`describe`: ``descriptor`` (D,) finite, ``rcs01`` the
        frame's normalised RCS values (1-D, finite, within [0, 1]; empty for a frame without
        points), ``key`` unique and hashable (see :func:`_check_key` for what ``save`` can write).
        Every defect is a DataError naming the value; nothing is inserted then."""
        _check_key(key)
        if key in self._key_set:
            raise DataError(f"key {key!r} is already in the place database")
        desc = self._check_descriptor(descriptor)
        rcs = _check_rcs(rcs01)
        if self._index is None:
            self._index = DescriptorIndex(desc.shape[1], self.config.retrieval)
        self._index.add(desc)
        self._keys.append(key)
        self._key_set.add(key)
        self._rcs.append(np.array(rcs, dtype=np.float32))  # a copy: the caller's may change
        self._hists.append(rcs_histogram(rcs, self._edges, self.config.rerank.epsilon))

    def query(
        self,
        frame_or_cloud,
        k: int = 5,
        exclude: Collection[Hashable] | Callable[[Hashable], bool] | None = None,
    ) -> list[PlaceCandidate]:
        """The ``k`` best places, best first. Pure: the database is not modified.

        ``exclude``: keys never to return, e.g. the most recent frames: a collection of keys
        (set, list, ...), a predicate on keys, or one key. A str, bytes or any other hashable
        that is not a collection (e.g. a ``NodeKey``) is one key; a tuple is one key when it is
        a key of the database, else a collection of keys.
        """
        desc, rcs = self.describe(frame_or_cloud)
        return self.query_descriptor(desc, rcs, k, exclude)

    def query_descriptor(
        self,
        descriptor: np.ndarray,
        rcs01: np.ndarray,
        k: int = 5,
        exclude: Collection[Hashable] | Callable[[Hashable], bool] | None = None,
    ) -> list[PlaceCandidate]:
        """As :meth:`query`, for a ``describe`` result; the same checks as ``add_descriptor``."""
        k = check_k(k)
        desc = self._check_descriptor(descriptor)
        rcs = _check_rcs(rcs01)
        if self._index is None or len(self._index) == 0:
            return []
        rr = self.config.rerank
        if callable(exclude):
            skip = exclude
        else:
            excluded = self._excluded_keys(exclude)
            n_ex = len(excluded & self._key_set)

            def skip(key) -> bool:
                return key in excluded

        m = max(k, rr.top_m if rr.enabled else k)
        m += len(self) if callable(exclude) else n_ex  # room for filtered-out keys
        res = self._index.search(desc, m)
        rows = [int(i) for i in res.indices[0] if not skip(self._keys[int(i)])]
        dist = {int(i): float(d) for i, d in zip(res.indices[0], res.distances[0], strict=True)}
        rows = rows[: max(k, rr.top_m) if rr.enabled else k]
        d = np.array([dist[r] for r in rows])
        if rr.enabled and rows:
            q = rcs_histogram(rcs, self._edges, rr.epsilon)
            kl = kl_divergence(q[None, :], np.stack([self._hists[r] for r in rows]))
            score = rr.alpha * kl + (1.0 - rr.alpha) * d
        else:
            score = d
        order = np.argsort(score, kind="stable")[:k]
        return [
            PlaceCandidate(self._keys[rows[j]], float(d[j]), float(score[j]), rank)
            for rank, j in enumerate(order)
        ]

    def _excluded_keys(self, exclude) -> set:
        if exclude is None:
            return set()
        if isinstance(exclude, (str, bytes)):
            return {exclude}
        if isinstance(exclude, tuple) and _hashable(exclude) and exclude in self._key_set:
            return {exclude}
        if isinstance(exclude, Collection):
            try:
                return set(exclude)
            except TypeError:
                bad = next(k for k in exclude if not _hashable(k))
                raise DataError(f"exclude: key {bad!r} is not hashable") from None
        if _hashable(exclude):
            return {exclude}
        raise DataError(
            f"exclude must be a key, a collection of keys or a predicate, "
            f"got {type(exclude).__name__}"
        )

    def _model_output_dim(self) -> int | None:
        try:
            dim = self.output_dim
        except Exception:  # a model config without a usable output_dim: not known
            return None
        return dim if dim is not None and dim >= 1 else None

    def _check_descriptor(self, descriptor) -> np.ndarray:
        """``descriptor`` as a (1, D) float32 row: one finite descriptor of the database's (or
        the model's) length, given as (D,) or (1, D)."""
        try:
            d = np.asarray(descriptor)
        except (TypeError, ValueError) as exc:
            raise DataError(f"descriptor is not a number array ({exc})") from None
        dim = self._index.dim if self._index is not None else self._model_dim
        want = f"{dim}" if dim is not None else "D"
        if not (d.ndim == 1 or (d.ndim == 2 and d.shape[0] == 1)) or d.size == 0:
            raise DataError(f"expected one descriptor of {want} values, got shape {d.shape}")
        if dim is not None and d.size != dim:
            raise DataError(f"expected one descriptor of {dim} values, got {d.size}")
        if d.dtype.kind not in "fiu":
            raise DataError(f"descriptor must hold numbers, got dtype {d.dtype}")
        d = d.astype(np.float32, copy=False).reshape(1, -1)
        if not np.isfinite(d).all():
            raise DataError("descriptor contains NaN or infinity")
        return d

    # ---- persistence -------------------------------------------------------------------------
    def save(self, path: str | Path) -> Path:
        """Write the database (descriptors, keys, RCS values, config) to one .npz, atomically."""
        from radarslam.io.atomic import atomic_open
        from radarslam.place_recognition.outputs import check_output_file

        path = check_output_file(path)
        try:
            keys_json = json.dumps(self._keys, allow_nan=False)
        except (TypeError, ValueError):
            bad = next((k for k in self._keys if not _saveable(k)), None)
            raise DataError(
                f"{path}: place key {bad!r} ({type(bad).__name__}) cannot be saved; keys must be "
                "str, int, finite float, None or flat tuples of them"
            ) from None
        dim = self._index.dim if self._index is not None else 0
        desc = self._index.matrix if self._index is not None else np.zeros((0, 0), np.float32)
        offsets = np.cumsum([0] + [len(r) for r in self._rcs]).astype(np.int64)
        rcs = np.concatenate(self._rcs) if self._rcs else np.zeros(0, np.float32)
        meta = {
            "format": DB_FORMAT,
            "config": self.config.model_dump(mode="json"),
            "seq_len": self.seq_len,
            "descriptor_dim": int(dim),
            # absolute, so that the database can be queried from any working directory
            "checkpoint": str(Path(self.checkpoint).resolve()) if self.checkpoint else None,
            "checkpoint_digest": self.checkpoint_digest,
        }
        with atomic_open(path, "wb") as fh:
            np.savez_compressed(
                fh,
                descriptors=desc,
                rcs01=rcs,
                offsets=offsets,
                keys_json=np.array(keys_json),
                meta_json=np.array(json.dumps(meta)),
            )
        return path

    @property
    def output_dim(self) -> int | None:
        """Descriptor length the model produces (None when the model does not say)."""
        cfg = getattr(self.model, "cfg", None)
        fn = getattr(cfg, "output_dim", None)
        return int(fn()) if callable(fn) else None

    @classmethod
    def load(
        cls,
        path: str | Path,
        model=None,
        checkpoint: str | Path | None = None,
        config: PlaceRecognizerConfig | None = None,
    ) -> PlaceRecognizer:
        """A recognizer holding a saved database (its stored config unless ``config`` is given).

        The model is the database's recorded checkpoint unless ``model`` or ``checkpoint`` is
        given; a model whose descriptors cannot be compared with the stored ones (another length,
        or other weights when both checkpoints' digests are known) is a CheckpointError.
        """
        path = Path(path)
        if not path.is_file():
            raise DataError(f"{path}: place database not found")
        db = _read_database(path)
        meta = db.meta
        if config is None:
            config = build_config(PlaceRecognizerConfig, meta["config"], f"{path} (config)")
        recorded = meta.get("checkpoint")
        if model is None and checkpoint is None and recorded:
            checkpoint = Path(recorded)
            if not checkpoint.is_file():
                raise CheckpointError(
                    f"{path}: recorded checkpoint {recorded} not found; pass --checkpoint"
                )
        rec = cls(model=model, checkpoint=checkpoint, config=config)
        used = str(rec.checkpoint) if rec.checkpoint is not None else "the given model"
        built = recorded or "an unrecorded model"
        want, have = meta.get("checkpoint_digest"), rec.checkpoint_digest
        if want and have and want != have:
            raise CheckpointError(
                f"{path}: built with checkpoint {built} (weights {want[:12]}), queried with {used} "
                f"(weights {have[:12]}); descriptors of different weights are not comparable "
                "(rebuild the database or pass the checkpoint it was built with)"
            )
        if rec.seq_len != meta["seq_len"]:
            raise CheckpointError(
                f"{path}: database built with seq_len={meta['seq_len']}, model uses {rec.seq_len}"
            )
        dim = db.descriptors.shape[1] if len(db.keys) else None
        out_dim = rec.output_dim
        if dim is not None and out_dim is not None and dim != out_dim:
            raise CheckpointError(
                f"{path}: holds {dim}-D descriptors (built with {built}) but {used} makes "
                f"{out_dim}-D descriptors; pass the checkpoint it was built with"
            )
        for i, key in enumerate(db.keys):
            rcs = db.rcs01[db.offsets[i] : db.offsets[i + 1]]
            rec.add_descriptor(db.descriptors[i], rcs, key)
        return rec


@dataclass(frozen=True)
class _StoredDatabase:
    meta: dict
    keys: list
    descriptors: np.ndarray  # (N, D) float32; (0, 0) when empty
    rcs01: np.ndarray  # (sum of points,) float32
    offsets: np.ndarray  # (N + 1,) int64


def _read_database(path: Path) -> _StoredDatabase:
    """Read and check a saved database; every defect is a one-line DataError naming ``path``."""
    from radarslam.place_recognition.dataset import read_npz

    try:
        arrays = read_npz(path)
    except ValueError as exc:
        raise DataError(f"{path}: not a place database ({exc})") from None
    for name in ("meta_json", "keys_json"):
        if name not in arrays:
            raise DataError(f"{path}: not a place database (no '{name}' array)")
    try:
        meta = json.loads(str(arrays["meta_json"]))
        keys = json.loads(str(arrays["keys_json"]))
    except ValueError as exc:
        raise DataError(f"{path}: not a place database (metadata is not JSON: {exc})") from None
    if not isinstance(meta, dict):
        raise DataError(f"{path}: metadata must be a JSON object, got {type(meta).__name__}")
    if meta.get("format") != DB_FORMAT:
        raise DataError(f"{path}: not a place database (format {meta.get('format')!r})")
    lacking = [k for k in ("config", "seq_len") if k not in meta]
    if lacking:
        raise DataError(f"{path}: metadata lacks {lacking}")
    if not isinstance(meta["config"], dict):
        raise DataError(f"{path}: metadata 'config' must be a JSON object")
    seq_len = meta["seq_len"]
    if isinstance(seq_len, bool) or not isinstance(seq_len, int) or seq_len < 1:
        raise DataError(f"{path}: metadata seq_len must be a positive integer, got {seq_len!r}")
    for name in ("checkpoint", "checkpoint_digest"):
        if meta.get(name) is not None and not isinstance(meta[name], str):
            raise DataError(f"{path}: metadata '{name}' must be a string or null")
    if not isinstance(keys, list):
        raise DataError(f"{path}: keys must be a JSON list, got {type(keys).__name__}")
    missing = [k for k in ("descriptors", "rcs01", "offsets") if k not in arrays]
    if missing:
        raise DataError(f"{path}: missing array(s) {missing}")
    desc, rcs, offsets = arrays["descriptors"], arrays["rcs01"], arrays["offsets"]
    n = len(keys)
    if desc.ndim != 2 or not np.issubdtype(desc.dtype, np.number):
        raise DataError(
            f"{path}: descriptors must be an (N, D) number array, got {desc.shape} {desc.dtype}"
        )
    if len(desc) != n or (n and desc.shape[1] == 0):
        raise DataError(f"{path}: {n} keys, {len(desc)} descriptors, inconsistent")
    dim = meta.get("descriptor_dim")
    if n and dim is not None and dim != desc.shape[1]:
        raise DataError(
            f"{path}: metadata says {dim}-D descriptors, the array is {desc.shape[1]}-D"
        )
    if not np.all(np.isfinite(desc)):
        raise DataError(f"{path}: descriptors contain NaN or infinity")
    if rcs.ndim != 1 or not np.issubdtype(rcs.dtype, np.number):
        raise DataError(f"{path}: rcs01 must be a 1-D number array, got {rcs.shape} {rcs.dtype}")
    if not np.all(np.isfinite(rcs)):
        raise DataError(f"{path}: rcs01 contains NaN or infinity")
    if rcs.size and (rcs.min() < -_RCS_TOLERANCE or rcs.max() > 1.0 + _RCS_TOLERANCE):
        raise DataError(
            f"{path}: rcs01 must lie in [0, 1] (normalised RCS), got values in "
            f"[{float(rcs.min()):.6g}, {float(rcs.max()):.6g}]"
        )
    if offsets.ndim != 1 or not np.issubdtype(offsets.dtype, np.integer):
        raise DataError(
            f"{path}: offsets must be a 1-D integer array, got {offsets.shape} {offsets.dtype}"
        )
    if len(offsets) != n + 1:
        raise DataError(f"{path}: {n} keys but {len(offsets)} offsets (expected {n + 1})")
    if offsets[0] != 0 or np.any(np.diff(offsets) < 0) or offsets[-1] != len(rcs):
        raise DataError(
            f"{path}: offsets must start at 0, never decrease and end at the number of RCS "
            f"values ({len(rcs)}); got {offsets[0]} .. {offsets[-1]}"
        )
    out_keys = [tuple(k) if isinstance(k, list) else k for k in keys]
    try:
        unique = len(set(out_keys)) == len(out_keys)
    except TypeError:  # a JSON object, or a list nested in a list
        raise DataError(f"{path}: keys must be strings, numbers or flat lists") from None
    if not unique:
        raise DataError(f"{path}: duplicate keys")
    return _StoredDatabase(
        meta,
        out_keys,
        desc.astype(np.float32, copy=False),
        rcs.astype(np.float32, copy=False),
        offsets.astype(np.int64),
    )


def _hashable(key) -> bool:
    try:
        hash(key)
    except TypeError:
        return False
    return True


_JSON_SCALARS = (str, int, float, type(None))  # bool is an int


def _saveable(key) -> bool:
    """Whether ``save`` writes ``key`` so that ``load`` gives an equal key back."""
    items = key if isinstance(key, tuple) else (key,)
    return all(
        isinstance(item, _JSON_SCALARS)
        and not isinstance(item, np.generic)
        and not (isinstance(item, float) and not math.isfinite(item))
        for item in items
    )


def _check_key(key) -> None:
    """A place key must be hashable. Keys are saved as JSON: a str, int, float, None or a tuple
    (saved as a list, loaded back as a tuple) must survive that unchanged, so a numpy scalar, a
    NaN/infinite float or a tuple holding anything else is refused here, not at ``save``. Other
    hashable objects (the SLAM pipeline's ``NodeKey``) serve in memory; ``save`` refuses them."""
    if not _hashable(key):
        raise DataError(f"place key {key!r} is not hashable ({type(key).__name__})")
    json_like = isinstance(key, (*_JSON_SCALARS, tuple, np.generic))
    if json_like and not _saveable(key):
        raise DataError(
            f"place key {key!r} ({type(key).__name__}) cannot be saved; keys must be str, int, "
            "finite float, None or flat tuples of them (convert numpy scalars with int()/str())"
        )


def _check_rcs(rcs01) -> np.ndarray:
    """``rcs01`` as a float32 1-D array of normalised RCS values (finite, in [0, 1]); empty is
    legal (a key frame without points in the image)."""
    try:
        r = np.asarray(rcs01)
    except (TypeError, ValueError) as exc:
        raise DataError(f"rcs01 is not a number array ({exc})") from None
    if r.ndim != 1 or r.dtype.kind not in "fiu":
        raise DataError(
            f"rcs01 must be a 1-D number array (normalised RCS), got shape {r.shape} {r.dtype}"
        )
    r = r.astype(np.float32, copy=False)
    if r.size:
        lo, hi = float(r.min()), float(r.max())
        if not (math.isfinite(lo) and math.isfinite(hi)):
            raise DataError("rcs01 contains NaN or infinity")
        if lo < -_RCS_TOLERANCE or hi > 1.0 + _RCS_TOLERANCE:
            raise DataError(
                f"rcs01 must lie in [0, 1] (normalised RCS), got values in [{lo:.6g}, {hi:.6g}]"
            )
    return r


def _check_point_fields(cloud: AccumulatedCloud) -> None:
    names = getattr(getattr(cloud.points, "dtype", None), "names", None) or ()
    missing = [n for n in _IMAGE_FIELDS if n not in names]
    if missing:
        raise DataError(
            f"cloud {cloud.sample_token or cloud.timestamp_us}: points lack field(s) {missing}"
        )


def _points_fingerprint(points) -> tuple | None:
    """A 128-bit BLAKE2b digest of the point fields the image is made of (values, dtypes and
    count); None when the points lack them (no caching: the frame's own error then)."""
    names = getattr(getattr(points, "dtype", None), "names", None) or ()
    if any(n not in names for n in _IMAGE_FIELDS):
        return None
    h = hashlib.blake2b(digest_size=16)
    for name in _IMAGE_FIELDS:
        col = np.ascontiguousarray(points[name])
        h.update(col.dtype.str.encode())
        h.update(col.data)
    return (len(points), h.digest())


def iter_scene_sequences(recognizer: PlaceRecognizer, reader, scene):
    """(sample_token, clouds oldest first) for every key frame of a scene that has a
    reference-channel key frame; each sequence holds up to ``recognizer.seq_len`` clouds."""
    ref = recognizer.config.accumulation.ref_channel
    window: list[AccumulatedCloud] = []
    for frame in reader.iter_frames(scene, key_frames_only=True, ref_channel=ref):
        if ref not in frame.sweeps:
            continue
        window = [*window, recognizer.cloud_from_reader(reader, frame.sample_token)]
        window = window[-recognizer.seq_len :]
        yield frame.sample_token, list(window)
