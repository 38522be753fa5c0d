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

The streaming parser lives in :mod:`radarslam.nuscenes.json_stream`, the compact records in
:mod:`radarslam.nuscenes.records` and the per-scene and quaternion checks in
:mod:`radarslam.nuscenes.table_checks`; this module builds :class:`NuScenesTables` from them.

What the streaming parser does not check: the content of skipped (non-radar) records beyond their
braces. Whatever is kept is fully decoded and validated; the list structure (``[``, records
separated by single commas, ``]``) is checked for the whole file.
"""

from __future__ import annotations

import hashlib
import logging
import os
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np

from radarslam.errors import DataError
from radarslam.geometry import make_transform, quat_norm_problem, quat_norms, quat_norms_ok
from radarslam.nuscenes.json_stream import (
    _TOKEN_RE,
    _field,
    _find_record,
    _floats,
    _iter_chunks,
    _load_json_list,
    _loads_many,
    _number_block,
    _radar_batches,
    _str_field,
    _text_array,
)
from radarslam.nuscenes.records import RadarIndex, SmallTables, TokenIndex, _bytes_array
from radarslam.nuscenes.table_checks import _scene_sample_problems, _warn_non_unit
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
        for i, rec in enumerate(logs_list):
            _str_field(p_log, rec, "location", i)
            _field(p_log, rec, "date_captured", i)
            logs[_str_field(p_log, rec, "token", i)] = rec

        scene_token_row: dict[str, int] = {}
        scene_row: dict[str, int] = {}
        for i, rec in enumerate(scenes):
            for key in ("token", "name", "log_token"):
                _str_field(p_scene, rec, key, i)
            for key in ("first_sample_token", "last_sample_token"):  # checked per scene
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
            s_token.append(_str_field(p_sample, rec, "token", i))
            ts = _field(p_sample, rec, "timestamp", i)
            if not isinstance(ts, int) or isinstance(ts, bool):
                raise DataError(
                    f"{p_sample}: record {rec['token']!r} timestamp {ts!r} is not an int"
                )
            s_time[i] = ts
            sc = _str_field(p_sample, rec, "scene_token", i)
            if sc not in scene_token_row:
                raise DataError(
                    f"{p_sample}: sample {rec['token']!r} refers to scene {sc!r} not in scene.json"
                )
            s_scene[i] = scene_token_row[sc]
            s_next_tok.append(_str_field(p_sample, rec, "next", i, optional=True))
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
            tok = _str_field(p_sensor, rec, "token", i)
            ch = _str_field(p_sensor, rec, "channel", i)
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
            cs_token.append(_str_field(p_cs, rec, "token", i))
            st = _str_field(p_cs, rec, "sensor_token", i)
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
                    cols[col].append(_text_array(p_sd, values, key, utf8=col == "filename"))
            except KeyError as exc:
                r = next(r for r in recs if exc.args[0] not in r)
                raise DataError(
                    f"{p_sd}: record {r.get('token')!r} has no {exc.args[0]!r} field"
                ) from None
            except TypeError:  # an unhashable token (a list, an object) used as a dict key
                for r in recs:
                    for key in ("calibrated_sensor_token", "sample_token"):
                        _str_field(p_sd, r, key)
                raise
            cs_rows.append(np.asarray(cs_i, dtype=np.int32))
            sample_rows.append(np.asarray(s_i, dtype=np.int32))
            stamps.append(np.asarray(ts, dtype=np.int64))
            keyf.append(np.asarray(kf, dtype=bool))

        def joined(k: str) -> np.ndarray:
            parts = cols.pop(k)
            return np.concatenate(parts) if parts else np.zeros(0, dtype="S1")

        token = joined("token")
        n = len(token)
        if n == 0:
            raise DataError(
                f"{p_sd}: no radar sample_data record (of a sensor whose channel is one of "
                f"{', '.join(RADAR_CHANNELS)})"
            )
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
            first = int(np.flatnonzero(~found)[0])
            record = token[int(np.flatnonzero(inverse == first)[0])].decode()
            raise DataError(
                f"{p_ego}: ego pose {uniq[first].decode()!r}, named by radar sample_data "
                f"{record!r} of {p_sd.name}, is missing ({int((~found).sum())} missing in all)"
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
