"""Lazy, compact loading of the nuScenes JSON tables that the radar path needs.

Only ``scene``, ``sample``, ``sample_data``, ``ego_pose``, ``calibrated_sensor``, ``sensor`` and
``log`` are read. The small ones are parsed with :mod:`json`. ``sample_data.json`` and
``ego_pose.json`` of ``v1.0-trainval`` hold millions of records (cameras and lidar too, about 1 GB
of text), so they are streamed in 8 MB windows: the list structure is checked with C-level counts,
radar records are found by a regular expression on their ``filename`` (cameras and lidar are never
decoded), the radar records of a window are decoded in one :func:`json.loads` call, and only the
radar ``sample_data`` and their ego poses are kept, as numpy arrays (:class:`RadarIndex`). Tokens
are looked up through sorted arrays (:class:`TokenIndex`): 32 bytes a record, not a dict entry.

The compact radar index can be cached on disk (``~/.cache/radarslam/nuscenes`` by default,
``$XDG_CACHE_HOME/radarslam/nuscenes``, or ``cache_dir``), keyed by the size and mtime of every
table file it was built from, so later start-ups on ``v1.0-trainval`` take a fraction of a second.
Nothing is ever written inside the dataroot.

What the streaming parser does not check: the content of skipped (non-radar) records beyond their
braces. Whatever is kept is fully decoded and validated; the list structure (``[``, records
separated by single commas, ``]``) is checked for the whole file.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import logging
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import numpy as np

from radarslam.errors import DataError
from radarslam.geometry import make_transform, quat_norm_problem, quat_norms, quat_norms_ok
from radarslam.types import RADAR_CHANNELS

log = logging.getLogger("radarslam.nuscenes")

VERSIONS: tuple[str, ...] = ("v1.0-mini", "v1.0-trainval", "v1.0-test")
TABLE_NAMES: tuple[str, ...] = (
    "scene",
    "sample",
    "sample_data",
    "ego_pose",
    "calibrated_sensor",
    "sensor",
    "log",
)
_CACHE_FORMAT = 1
_CHUNK_BYTES = 8 << 20  # streaming window: bounds the transient memory
_SEP_RE = re.compile(rb"\}\s*,\s*\{")
# the filename of a radar sample_data names its channel folder ("samples/RADAR_FRONT/...")
_RADAR_FILENAME_RE = re.compile(rb'"filename"\s*:\s*"[^"]*RADAR_')
_TOKEN_RE = re.compile(rb'"token"\s*:\s*"([^"]*)"')
_WS = b" \t\r\n"


# --------------------------------------------------------------------------------------------
# token lookup
# --------------------------------------------------------------------------------------------
class TokenIndex:
    """token -> row lookup over a fixed-width bytes array, through a sorted copy (no dict)."""

    def __init__(self, tokens: np.ndarray, what: str = "token"):
        self.tokens = tokens
        self.order = np.argsort(tokens, kind="stable")
        self._sorted = tokens[self.order]
        self.what = what
        if len(tokens) > 1:
            dup = self._sorted[1:] == self._sorted[:-1]
            if dup.any():
                first = self._sorted[1:][dup][0].decode()
                raise DataError(f"{what}: token {first!r} appears more than once")

    def __len__(self) -> int:
        return len(self.tokens)

    def find_many(self, queries: np.ndarray) -> np.ndarray:
        """Row of each query, -1 where absent (queries: bytes array)."""
        queries = np.asarray(queries)
        if len(self._sorted) == 0 or len(queries) == 0:
            return np.full(len(queries), -1, dtype=np.int64)
        if queries.dtype.kind != "S":
            queries = queries.astype(self._sorted.dtype)
        pos = np.searchsorted(self._sorted, queries)
        pos_c = np.minimum(pos, len(self._sorted) - 1)
        hit = self._sorted[pos_c] == queries
        return np.where(hit, self.order[pos_c], -1)

    def find(self, token: str) -> int:
        try:
            q = np.array([token.encode("ascii")])
        except UnicodeEncodeError:
            return -1
        if q.dtype.itemsize > self._sorted.dtype.itemsize:
            return -1  # longer than any stored token: cannot be one of them
        return int(self.find_many(q)[0])


def _bytes_array(values: list[bytes]) -> np.ndarray:
    if not values:
        return np.zeros(0, dtype="S1")
    return np.array(values, dtype=bytes)


# --------------------------------------------------------------------------------------------
# compact records
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True, eq=False)
class RadarIndex:
    """All radar ``sample_data`` records of a version, one row each, plus their ego poses."""

    token: np.ndarray  # S, sample_data token
    sample: np.ndarray  # int32 row in SmallTables.sample_*
    calibrated_sensor: np.ndarray  # int32 row in SmallTables.cs_*
    channel: np.ndarray  # int8 index into RADAR_CHANNELS
    timestamp_us: np.ndarray  # int64
    is_key_frame: np.ndarray  # bool
    filename: np.ndarray  # S, relative to the dataroot
    prev: np.ndarray  # int32 row, -1 at the start of a chain
    next: np.ndarray  # int32 row, -1 at the end of a chain
    ego_translation: np.ndarray  # (N, 3) float64
    ego_rotation: np.ndarray  # (N, 4) float64, w x y z

    def __len__(self) -> int:
        return len(self.token)

    def arrays(self) -> dict[str, np.ndarray]:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.arrays().values())


@dataclass(frozen=True, eq=False)
class SmallTables:
    """scene, sample, log, sensor and calibrated_sensor, in plain Python / numpy form."""

    scenes: list[dict]  # scene.json records (as read)
    logs: dict[str, dict]  # log token -> record
    sample_token: np.ndarray  # S
    sample_timestamp_us: np.ndarray  # int64
    sample_scene: np.ndarray  # int32 row in scenes
    sample_next: np.ndarray  # int32 row, -1 at the end
    sample_row: dict[str, int]  # sample token -> row
    cs_token: list[str]
    cs_row: dict[str, int]
    cs_channel: np.ndarray  # int8 RADAR_CHANNELS index, -1 for non-radar sensors
    cs_translation: np.ndarray  # (M, 3)
    cs_rotation: np.ndarray  # (M, 4)
    scene_row: dict[str, int]  # scene name -> row
    #: scene row -> one-line reason, for scenes that cannot be read (see check_scene)
    scene_problems: dict[int, str] = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# JSON helpers
# --------------------------------------------------------------------------------------------
def _load_json_list(path: Path) -> list:
    try:
        with path.open("rb") as fh:
            data = json.load(fh)
    except FileNotFoundError:
        raise DataError(f"{path}: table file is missing") from None
    except json.JSONDecodeError as exc:
        raise DataError(
            f"{path}: corrupt JSON (line {exc.lineno} column {exc.colno}: {exc.msg})"
        ) from None
    except UnicodeDecodeError:
        raise DataError(f"{path}: corrupt JSON (not UTF-8 text)") from None
    except OSError as exc:
        raise DataError(f"{path}: cannot read table ({exc.strerror})") from None
    if not isinstance(data, list):
        raise DataError(f"{path}: expected a JSON list of records, got {type(data).__name__}")
    for i, rec in enumerate(data):
        if not isinstance(rec, dict):
            raise DataError(f"{path}: record {i} is {type(rec).__name__}, expected an object")
    return data


def _field(path: Path, rec: dict, key: str, i: int | None = None):
    try:
        return rec[key]
    except KeyError:
        where = f"record {rec.get('token', i)!r}"
        raise DataError(f"{path}: {where} has no {key!r} field") from None


def _floats(path: Path, rec: dict, key: str, n: int) -> list[float]:
    value = _field(path, rec, key)
    if (
        not isinstance(value, list)
        or len(value) != n
        or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    ):
        raise DataError(
            f"{path}: record {rec.get('token')!r} field {key!r} is {value!r}, expected {n} numbers"
        )
    return value


def _iter_chunks(path: Path) -> Iterator[tuple[bytes, int]]:
    """Yield (body, byte offset) pieces of a JSON list of flat ``{...}`` records, streaming.

    Each body holds whole records and their separators. The list structure (``[``, records
    separated by exactly one comma, ``]``) is checked in bulk with C-speed regex/bytes operations;
    nothing is decoded: callers pick the records worth :func:`json.loads`.
    """
    try:
        fh = path.open("rb")
    except FileNotFoundError:
        raise DataError(f"{path}: table file is missing") from None
    except OSError as exc:
        raise DataError(f"{path}: cannot read table ({exc.strerror})") from None
    with fh:
        carry = b""
        base = 0  # file offset of carry[0]
        started = False
        while True:
            chunk = fh.read(_CHUNK_BYTES)
            if not chunk:
                break
            buf = carry + chunk if carry else chunk
            last = buf.rfind(b"}")
            if last < 0:
                carry = buf
                continue
            body = buf[: last + 1]
            _check_structure(path, body, base, started)
            started = True
            yield body, base
            carry = buf[last + 1 :]
            base += last + 1
        tail = carry.translate(None, _WS)
        if tail != (b"]" if started else b"[]"):
            what = (
                "truncated" if not tail.endswith(b"]") else f"unexpected {tail[:20]!r} at the end"
            )
            raise DataError(f"{path}: corrupt JSON ({what}, after byte {base})")


def _check_structure(path: Path, body: bytes, base: int, started: bool) -> None:
    """A list of flat records: '[' (or ',' after a previous chunk), then records separated by
    exactly one comma. Done with C-speed counts, no per-record Python work."""
    n = body.count(b"{")
    if n == 0 or body.count(b"}") != n:
        raise DataError(
            f"{path}: corrupt JSON (unbalanced braces between bytes {base} and {base + len(body)})"
        )
    head = body[: body.find(b"{")].translate(None, _WS)
    if head != (b"," if started else b"["):
        what = "expected '[' at the start of the list" if not started else f"unexpected {head!r}"
        raise DataError(f"{path}: corrupt JSON ({what}, near byte {base})")
    seps = len(_SEP_RE.findall(body))
    if seps != n - 1:
        raise DataError(
            f"{path}: corrupt JSON (records between bytes {base} and {base + len(body)} are not "
            f"flat objects separated by single commas)"
        )


def _radar_batches(path: Path) -> Iterator[list[tuple[bytes, int]]]:
    """Per chunk, the (raw bytes, offset) of the records whose filename names a radar channel.
    The search runs in C over the other records (cameras, lidar), which are never decoded."""
    for body, base in _iter_chunks(path):
        pieces = []
        for m in _RADAR_FILENAME_RE.finditer(body):
            start = body.rfind(b"{", 0, m.start())
            end = body.find(b"}", m.end()) + 1
            pieces.append((body[start:end], base + start))
        if pieces:
            yield pieces


def _loads_many(path: Path, pieces: list[tuple[bytes, int]]) -> list[dict]:
    """Decode many records in one C call; on failure, find the bad one for the message."""
    try:
        return json.loads(b"[" + b",".join(raw for raw, _ in pieces) + b"]")
    except (json.JSONDecodeError, UnicodeDecodeError):
        for raw, offset in pieces:
            _loads(path, raw, offset)
        raise DataError(f"{path}: corrupt JSON") from None


def _text_array(path: Path, values: list, what: str, utf8: bool = False) -> np.ndarray:
    if not set(map(type, values)) <= {str}:
        bad = next(v for v in values if type(v) is not str)
        raise DataError(f"{path}: a radar record has {what} {bad!r}, expected a string")
    if not values:
        return np.zeros(0, dtype="S1")
    if utf8:
        return np.array([v.encode("utf-8") for v in values], dtype=bytes)
    try:
        return np.array(values, dtype=bytes)  # ASCII tokens
    except UnicodeEncodeError:
        raise DataError(f"{path}: a radar record has a non-ASCII {what}") from None


def _number_block(
    path: Path, recs: list[dict], key: str, n: int, check_types: bool = False
) -> np.ndarray:
    """(len(recs), n) float array of one list-valued field, validated in bulk.

    The dtype numpy infers rejects strings ("1" would convert under dtype=float64), nulls and
    nested lists in C; booleans mix into a float array unnoticed, so ``check_types`` (set when the
    JSON text holds ``true``/``false`` at all) checks each element's type as well."""
    try:
        values = [r[key] for r in recs]
        arr = np.array(values)  # numbers only -> int64/float64; a string -> <U, null -> object
        if (
            arr.shape == (len(recs), n)
            and arr.dtype.kind in "fi"
            and set(map(type, values)) <= {list}
            and (
                not check_types
                or set(map(type, itertools.chain.from_iterable(values))) <= {int, float}
            )
        ):
            return arr.astype(np.float64, copy=False)
    except (KeyError, TypeError, ValueError, OverflowError):
        pass
    for r in recs:  # slow path: name the bad record
        _floats(path, r, key, n)
    raise DataError(f"{path}: field {key!r} is malformed")


def _loads(path: Path, raw: bytes, offset: int) -> dict:
    try:
        return json.loads(raw)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise DataError(f"{path}: corrupt JSON in the record at byte {offset} ({exc})") from None


def _find_record(path: Path, token: bytes) -> dict | None:
    """The record of ``token`` in a streamed table, or None (slow: for error messages only)."""
    pattern = re.compile(rb'"token"\s*:\s*"' + re.escape(token) + rb'"')
    for body, base in _iter_chunks(path):
        m = pattern.search(body)
        if m:
            start = body.rfind(b"{", 0, m.start())
            end = body.find(b"}", m.end()) + 1
            return _loads(path, body[start:end], base + start)
    return None


def _scene_sample_problems(
    p_scene: Path, p_sample: Path, scenes: list[dict], sample_row: dict, s_scene: np.ndarray
) -> dict[int, str]:
    """Scene row -> why it cannot be read (no samples, or a first/last sample token that is not
    its own), for the scenes that have such a problem. Kept per scene: a broken scene must not
    stop runs on the others, only a run that asks for it."""
    count = np.bincount(s_scene, minlength=len(scenes))
    out: dict[int, str] = {}

    def row_of(tok) -> int | None:
        return sample_row.get(tok) if isinstance(tok, str) else None

    for row, rec in enumerate(scenes):
        name = rec["name"]
        problems = []
        for key in ("first_sample_token", "last_sample_token"):
            tok = rec[key]
            j = row_of(tok)
            if tok == "":
                problems.append(f"{key} is empty")
            elif j is None:
                problems.append(f"{key} {tok!r} is not in {p_sample.name}")
            elif s_scene[j] != row:
                other = scenes[s_scene[j]]["name"]
                problems.append(f"{key} {tok!r} belongs to scene {other!r}")
        if count[row] == 0:
            why = f" ({problems[0]})" if problems else ""
            out[row] = (
                f"{p_scene}: scene {name!r} has no samples: no record of {p_sample.name} has "
                f"scene_token {rec['token']!r}{why}"
            )
        elif problems:
            out[row] = f"{p_scene}: scene {name!r} {problems[0]}"
    return out


def _warn_non_unit(
    path: Path, what: str, tokens, quats: np.ndarray, norms: np.ndarray | None = None
) -> None:
    """One warning per table when rotation quaternions are not unit (they are normalised)."""
    if norms is None:
        norms = quat_norms(quats)
    off = np.abs(norms - 1.0) > 1e-3
    if off.any():
        i = int(np.flatnonzero(off)[0])
        tok = tokens[i].decode() if isinstance(tokens[i], bytes) else tokens[i]
        log.warning(
            "%s: %d %s(s) have a rotation quaternion whose norm is not 1 (first: %r, norm %.6g); "
            "they are normalised",
            path,
            int(off.sum()),
            what,
            tok,
            float(norms[i]),
        )


# --------------------------------------------------------------------------------------------
# the tables
# --------------------------------------------------------------------------------------------
def default_cache_dir() -> Path:
    root = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(root) / "radarslam" / "nuscenes"


class NuScenesTables:
    """The radar-relevant tables of one ``DATAROOT/<version>``, loaded on first use.

    ``use_cache``: read/write the compact radar index in ``cache_dir`` (never inside the dataroot).
    The cache is only written when ``sample_data.json`` is at least ``cache_min_bytes`` large
    (v1.0-mini parses in well under a second and needs none).
    """

    def __init__(
        self,
        dataroot: str | Path,
        version: str = "v1.0-mini",
        *,
        use_cache: bool = True,
        cache_dir: str | Path | None = None,
        cache_min_bytes: int = 32 << 20,
    ):
        self.dataroot = Path(dataroot).expanduser()
        self.version = version
        if not self.dataroot.is_dir():
            raise DataError(f"{self.dataroot}: dataroot does not exist or is not a directory")
        if version not in VERSIONS:
            raise DataError(f"unknown nuScenes version {version!r}; expected one of {VERSIONS}")
        self.table_dir = self.dataroot / version
        if not self.table_dir.is_dir():
            present = sorted(p.name for p in self.dataroot.glob("v1.0-*") if p.is_dir())
            hint = (
                "; pass the folder above it as the dataroot"
                if self.dataroot.name in VERSIONS or (self.dataroot / "scene.json").is_file()
                else ""
            )
            raise DataError(
                f"{self.table_dir}: version folder is missing (present: {present or 'none'})" + hint
            )
        for name in TABLE_NAMES:
            if not (self.table_dir / f"{name}.json").is_file():
                raise DataError(f"{self.table_dir / f'{name}.json'}: table file is missing")
        self.use_cache = use_cache
        self.cache_dir = Path(cache_dir).expanduser() if cache_dir is not None else None
        self.cache_min_bytes = cache_min_bytes
        self._small: SmallTables | None = None
        self._radar: RadarIndex | None = None
        self._radar_tokens: TokenIndex | None = None
        self.cache_hit: bool | None = None  # set once the radar index is loaded

    def path(self, name: str) -> Path:
        return self.table_dir / f"{name}.json"

    # ---- small tables ------------------------------------------------------------------------
    @property
    def small(self) -> SmallTables:
        if self._small is None:
            self._small = self._load_small()
        return self._small

    def _load_small(self) -> SmallTables:
        p_scene, p_sample, p_log = self.path("scene"), self.path("sample"), self.path("log")
        p_sensor, p_cs = self.path("sensor"), self.path("calibrated_sensor")
        scenes = _load_json_list(p_scene)
        logs_list = _load_json_list(p_log)
        sensors = _load_json_list(p_sensor)
        cs_list = _load_json_list(p_cs)
        samples = _load_json_list(p_sample)

        logs = {}
        for rec in logs_list:
            for key in ("location", "date_captured"):
                _field(p_log, rec, key)
            logs[_field(p_log, rec, "token")] = rec

        scene_token_row: dict[str, int] = {}
        scene_row: dict[str, int] = {}
        for i, rec in enumerate(scenes):
            for key in ("token", "name", "log_token", "first_sample_token", "last_sample_token"):
                _field(p_scene, rec, key, i)
            if rec["log_token"] not in logs:
                raise DataError(
                    f"{p_scene}: scene {rec['name']!r} refers to log {rec['log_token']!r} "
                    f"that is not in {p_log.name}"
                )
            scene_token_row[rec["token"]] = i
            if rec["name"] in scene_row:
                raise DataError(f"{p_scene}: scene name {rec['name']!r} appears twice")
            scene_row[rec["name"]] = i

        n = len(samples)
        s_token = []
        s_time = np.zeros(n, dtype=np.int64)
        s_scene = np.zeros(n, dtype=np.int32)
        s_next_tok = []
        for i, rec in enumerate(samples):
            s_token.append(_field(p_sample, rec, "token", i))
            ts = _field(p_sample, rec, "timestamp", i)
            if not isinstance(ts, int) or isinstance(ts, bool):
                raise DataError(
                    f"{p_sample}: record {rec['token']!r} timestamp {ts!r} is not an int"
                )
            s_time[i] = ts
            sc = _field(p_sample, rec, "scene_token", i)
            if sc not in scene_token_row:
                raise DataError(
                    f"{p_sample}: sample {rec['token']!r} refers to scene {sc!r} not in scene.json"
                )
            s_scene[i] = scene_token_row[sc]
            s_next_tok.append(_field(p_sample, rec, "next", i))
        sample_row = {t: i for i, t in enumerate(s_token)}
        if len(sample_row) != n:
            raise DataError(f"{p_sample}: duplicate sample tokens")
        s_next = np.full(n, -1, dtype=np.int32)
        for i, t in enumerate(s_next_tok):
            if t:
                j = sample_row.get(t)
                if j is None:
                    raise DataError(f"{p_sample}: sample {s_token[i]!r} next {t!r} is not a sample")
                s_next[i] = j
        scene_problems = _scene_sample_problems(p_scene, p_sample, scenes, sample_row, s_scene)

        sensor_channel = {}
        for i, rec in enumerate(sensors):
            tok = _field(p_sensor, rec, "token", i)
            ch = _field(p_sensor, rec, "channel", i)
            modality = rec.get("modality", "radar" if str(ch).startswith("RADAR") else "")
            sensor_channel[tok] = (
                RADAR_CHANNELS.index(ch) if (modality == "radar" and ch in RADAR_CHANNELS) else -1
            )
        m = len(cs_list)
        cs_token = []
        cs_channel = np.full(m, -1, dtype=np.int8)
        cs_t = np.zeros((m, 3))
        cs_q = np.zeros((m, 4))
        for i, rec in enumerate(cs_list):
            cs_token.append(_field(p_cs, rec, "token", i))
            st = _field(p_cs, rec, "sensor_token", i)
            if st not in sensor_channel:
                raise DataError(f"{p_cs}: record {rec['token']!r} sensor {st!r} not in sensor.json")
            cs_channel[i] = sensor_channel[st]
            if cs_channel[i] >= 0:
                cs_t[i] = _floats(p_cs, rec, "translation", 3)
                cs_q[i] = _floats(p_cs, rec, "rotation", 4)
                if not np.isfinite(cs_t[i]).all():
                    raise DataError(
                        f"{p_cs}: record {rec['token']!r} has a non-finite translation "
                        f"{cs_t[i].tolist()}"
                    )
                why = quat_norm_problem(float(quat_norms(cs_q[i])))
                if why is not None:
                    raise DataError(
                        f"{p_cs}: record {rec['token']!r} has a degenerate rotation "
                        f"{cs_q[i].tolist()}: the quaternion {why}"
                    )
        radar_cs = np.flatnonzero(cs_channel >= 0)
        _warn_non_unit(
            p_cs, "calibrated_sensor record", [cs_token[i] for i in radar_cs], cs_q[radar_cs]
        )
        return SmallTables(
            scenes=scenes,
            logs=logs,
            sample_token=_bytes_array([t.encode() for t in s_token]),
            sample_timestamp_us=s_time,
            sample_scene=s_scene,
            sample_next=s_next,
            sample_row=sample_row,
            cs_token=cs_token,
            cs_row={t: i for i, t in enumerate(cs_token)},
            cs_channel=cs_channel,
            cs_translation=cs_t,
            cs_rotation=cs_q,
            scene_row=scene_row,
            scene_problems=scene_problems,
        )

    def check_scene(self, row: int) -> None:
        """:class:`DataError` when the scene of this row cannot be read (no samples, or a first
        or last sample token that is not its own)."""
        why = self.small.scene_problems.get(row)
        if why is not None:
            raise DataError(why)

    def ego_from_sensor(self, cs_row: int) -> np.ndarray:
        s = self.small
        return make_transform(s.cs_translation[cs_row], s.cs_rotation[cs_row])

    # ---- radar index -------------------------------------------------------------------------
    @property
    def radar(self) -> RadarIndex:
        if self._radar is None:
            self._radar = self._load_radar()
        return self._radar

    @property
    def radar_tokens(self) -> TokenIndex:
        if self._radar_tokens is None:
            self._radar_tokens = TokenIndex(self.radar.token, what=str(self.path("sample_data")))
        return self._radar_tokens

    def _cache_key(self) -> tuple[str, Path]:
        parts = [f"format={_CACHE_FORMAT}", str(self.table_dir.resolve())]
        for name in TABLE_NAMES:
            st = self.path(name).stat()
            parts.append(f"{name}:{st.st_size}:{st.st_mtime_ns}")
        key = hashlib.sha256("\n".join(parts).encode()).hexdigest()
        folder = self.cache_dir or default_cache_dir()
        return key, folder / f"{self.version}-{key[:20]}.npz"

    def _load_radar(self) -> RadarIndex:
        cache_file = None
        key = ""
        if self.use_cache:
            key, cache_file = self._cache_key()
            cached = self._read_cache(cache_file, key)
            if cached is not None:
                self.cache_hit = True
                return cached
        self.cache_hit = False
        index = self._build_radar()
        if (
            cache_file is not None
            and self.path("sample_data").stat().st_size >= self.cache_min_bytes
        ):
            self._write_cache(cache_file, key, index)
        return index

    def _read_cache(self, cache_file: Path, key: str) -> RadarIndex | None:
        if not cache_file.is_file():
            return None
        try:
            with np.load(cache_file, allow_pickle=False) as z:
                if str(z["key"]) != key:
                    return None
                arrays = {f.name: z[f.name] for f in fields(RadarIndex)}
            return RadarIndex(**arrays)
        except Exception as exc:  # a damaged cache is rebuilt, never fatal
            log.warning("ignoring unreadable radar index cache %s (%s)", cache_file, exc)
            return None

    def _write_cache(self, cache_file: Path, key: str, index: RadarIndex) -> None:
        from radarslam.io.atomic import atomic_open

        try:
            with atomic_open(cache_file, "wb") as fh:
                arrays: dict[str, Any] = {"key": np.array(key), **index.arrays()}
                np.savez(fh, **arrays)
        except OSError as exc:  # a read-only home must not stop the reader
            log.warning("could not write the radar index cache %s (%s)", cache_file, exc)

    def _build_radar(self) -> RadarIndex:
        small = self.small
        p_sd = self.path("sample_data")
        p_ego = self.path("ego_pose")
        cs_radar = {t: i for i, t in enumerate(small.cs_token) if small.cs_channel[i] >= 0}

        cols: dict[str, list] = {k: [] for k in ("token", "prev", "next", "ego", "filename")}
        # per-window numpy pieces, concatenated at the end (no Python int per record survives)
        sample_rows: list[np.ndarray] = []
        cs_rows: list[np.ndarray] = []
        stamps: list[np.ndarray] = []
        keyf: list[np.ndarray] = []
        keys = {"token": "token", "prev": "prev", "next": "next", "ego": "ego_pose_token"}
        keys["filename"] = "filename"
        for pieces in _radar_batches(p_sd):
            recs = _loads_many(p_sd, pieces)
            # column-wise comprehensions: several times faster than one loop with appends
            try:
                cs_i = [cs_radar.get(r["calibrated_sensor_token"], -1) for r in recs]
                if -1 in cs_i:
                    for r, c in zip(recs, cs_i, strict=True):
                        if c < 0 and r["calibrated_sensor_token"] not in small.cs_row:
                            raise DataError(
                                f"{p_sd}: record {r.get('token')!r} calibrated_sensor_token "
                                f"{r['calibrated_sensor_token']!r} is not in calibrated_sensor.json"
                            )
                    # not radars after all (a camera file named after a radar?)
                    recs = [r for r, c in zip(recs, cs_i, strict=True) if c >= 0]
                    cs_i = [c for c in cs_i if c >= 0]
                s_i = [small.sample_row.get(r["sample_token"], -1) for r in recs]
                if -1 in s_i:
                    r = recs[s_i.index(-1)]
                    raise DataError(
                        f"{p_sd}: record {r.get('token')!r} sample_token {r['sample_token']!r} "
                        "is not in sample.json"
                    )
                ts = [r["timestamp"] for r in recs]
                if not set(map(type, ts)) <= {int}:
                    r = next(r for r in recs if type(r["timestamp"]) is not int)
                    raise DataError(
                        f"{p_sd}: record {r.get('token')!r} timestamp {r['timestamp']!r} "
                        "is not an int"
                    )
                kf = [bool(r["is_key_frame"]) for r in recs]
                for col, key in keys.items():
                    values = [r[key] for r in recs]
                    cols[col].append(_text_array(p_sd, values, col, utf8=col == "filename"))
            except KeyError as exc:
                r = next(r for r in recs if exc.args[0] not in r)
                raise DataError(
                    f"{p_sd}: record {r.get('token')!r} has no {exc.args[0]!r} field"
                ) from None
            cs_rows.append(np.asarray(cs_i, dtype=np.int32))
            sample_rows.append(np.asarray(s_i, dtype=np.int32))
            stamps.append(np.asarray(ts, dtype=np.int64))
            keyf.append(np.asarray(kf, dtype=bool))

        def joined(k: str) -> np.ndarray:
            parts = cols.pop(k)
            return np.concatenate(parts) if parts else np.zeros(0, dtype="S1")

        token = joined("token")
        n = len(token)
        tindex = TokenIndex(token, what=str(p_sd))

        def chain(arr: np.ndarray, which: str) -> np.ndarray:
            rows = tindex.find_many(arr)
            bad = (rows < 0) & (arr != b"")
            if bad.any():
                i = int(np.flatnonzero(bad)[0])
                role = f"the {which} of radar record {token[i].decode()!r}"
                raise DataError(self._why_not_radar(arr[i], role))
            return rows.astype(np.int32)

        prev_rows = chain(joined("prev"), "prev")
        next_rows = chain(joined("next"), "next")
        ego_tok = joined("ego")
        filename = joined("filename")

        # One ego pose per sample_data in nuScenes, but tolerate sharing.
        uniq, inverse = np.unique(ego_tok, return_inverse=True)
        del ego_tok
        uindex = TokenIndex(uniq, what=str(p_ego))
        u_t = np.full((len(uniq), 3), np.nan)
        u_q = np.full((len(uniq), 4), np.nan)
        found = np.zeros(len(uniq), dtype=bool)
        for body, base in _iter_chunks(p_ego):
            # tokens of every record in C; decode only the records a radar sweep needs
            toks = _TOKEN_RE.findall(body)
            if len(toks) != body.count(b"{"):
                raise DataError(
                    f"{p_ego}: a record between bytes {base} and {base + len(body)} has no "
                    f"'token' field (or more than one)"
                )
            rows = uindex.find_many(_bytes_array(toks))
            hits = np.flatnonzero(rows >= 0)
            if len(hits) == 0:
                continue
            pieces = []
            pos = 0
            for h in hits:  # in file order: each search starts where the previous one ended
                at = body.find(b'"' + toks[h] + b'"', pos)
                start = body.rfind(b"{", 0, at)
                pos = body.find(b"}", at) + 1
                pieces.append((body[start:pos], base + start))
            recs = _loads_many(p_ego, pieces)
            dest = rows[hits]
            bools = b"true" in body or b"false" in body  # C search; never in real ego poses
            u_t[dest] = _number_block(p_ego, recs, "translation", 3, bools)
            u_q[dest] = _number_block(p_ego, recs, "rotation", 4, bools)
            found[dest] = True
        if not found.all():
            missing = uniq[~found][0].decode()
            raise DataError(
                f"{p_ego}: ego pose {missing!r} of a radar sample_data is missing "
                f"({int((~found).sum())} missing in all)"
            )
        norm_q = quat_norms(u_q)
        finite_q, finite_t = np.isfinite(u_q).all(axis=1), np.isfinite(u_t).all(axis=1)
        bad = ~finite_q | ~finite_t | ~quat_norms_ok(norm_q)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            what = (
                "a non-finite rotation"
                if not finite_q[i]
                else "a non-finite translation"
                if not finite_t[i]
                else "a zero rotation quaternion"
                if norm_q[i] == 0
                else f"a rotation quaternion that {quat_norm_problem(float(norm_q[i]))}"
            )
            raise DataError(
                f"{p_ego}: ego pose {uniq[i].decode()!r} has {what} (rotation {u_q[i].tolist()}, "
                f"translation {u_t[i].tolist()}; {int(bad.sum())} bad ego pose(s) in all)"
            )
        _warn_non_unit(p_ego, "ego pose", uniq, u_q, norm_q)
        if n:
            log.debug("indexed %d radar sample_data records of %s", n, self.table_dir)

        def cat(parts: list[np.ndarray], dtype) -> np.ndarray:
            return np.concatenate(parts).astype(dtype) if parts else np.zeros(0, dtype=dtype)

        cs_arr = cat(cs_rows, np.int32)
        return RadarIndex(
            token=token,
            sample=cat(sample_rows, np.int32),
            calibrated_sensor=cs_arr,
            channel=small.cs_channel[cs_arr.astype(np.int64)].astype(np.int8),
            timestamp_us=cat(stamps, np.int64),
            is_key_frame=cat(keyf, bool),
            filename=filename,
            prev=prev_rows,
            next=next_rows,
            ego_translation=u_t[inverse].reshape(n, 3),
            ego_rotation=u_q[inverse].reshape(n, 4),
        )

    def _why_not_radar(self, tok: bytes, role: str) -> str:
        """Error message for a prev/next token that is not a radar record: look the token up in
        sample_data.json (error path only) and say what is wrong with its record."""
        p_sd = self.path("sample_data")
        name = tok.decode(errors="replace")
        rec = _find_record(p_sd, tok)
        if rec is None:
            return f"{p_sd}: sample_data {name!r} ({role}) is not in {p_sd.name}"
        where = f"{p_sd}: sample_data record {name!r} ({role})"
        fn = rec.get("filename")
        cs_tok = rec.get("calibrated_sensor_token")
        cs = self.small.cs_row.get(cs_tok, -1) if isinstance(cs_tok, str) else -1
        cs_radar = cs >= 0 and self.small.cs_channel[cs] >= 0
        tail = ", though its calibrated_sensor is a radar's" if cs_radar else ""
        if "filename" not in rec:
            return f"{where} has no 'filename' field{tail}"
        if not isinstance(fn, str):
            return f"{where} has filename {fn!r}, expected a string"
        if "RADAR_" not in fn:
            return (
                f"{where} has filename {fn!r}, not a radar file (samples/RADAR_*/ or "
                f"sweeps/RADAR_*/){tail}"
            )
        return (
            f"{where} has a radar filename {fn!r} but calibrated_sensor_token "
            f"{cs_tok!r} is not a radar's calibration"
        )

    def world_from_ego(self, row: int) -> np.ndarray:
        r = self.radar
        return make_transform(r.ego_translation[row], r.ego_rotation[row])
