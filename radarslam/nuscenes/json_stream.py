"""Streaming reads of the nuScenes JSON tables, checked as they are read.

The small tables are parsed whole (:func:`_load_json_list`). ``sample_data.json`` and
``ego_pose.json`` are streamed in windows (:func:`_iter_chunks`): the list structure is checked
with C-level counts, and only the records a caller picks are decoded. Every failure is a
:class:`~radarslam.errors.DataError` that names the file and the record or byte offset.
"""

from __future__ import annotations

import itertools
import json
import re
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from radarslam.errors import DataError

_CHUNK_BYTES = 8 << 20  # streaming window: bounds the transient memory
_SEP_RE = re.compile(rb"\}\s*,\s*\{")
# the filename of a radar sample_data names its channel folder ("samples/RADAR_FRONT/...")
_RADAR_FILENAME_RE = re.compile(rb'"filename"\s*:\s*"[^"]*RADAR_')
_TOKEN_RE = re.compile(rb'"token"\s*:\s*"([^"]*)"')
_WS = b" \t\r\n"


def _json_type(value) -> str:
    """What a decoded JSON value is, in JSON's words."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "a boolean"
    if isinstance(value, (int, float)):
        return "a number"
    if isinstance(value, str):
        return "a string"
    return "a list" if isinstance(value, list) else "an object"


def _shape_problem(path: Path, data) -> DataError | None:
    """Why decoded JSON is not a list of records (objects), or None."""
    if not isinstance(data, list):
        return DataError(f"{path}: expected a JSON list of records, got {_json_type(data)}")
    for i, rec in enumerate(data):
        if not isinstance(rec, dict):
            return DataError(f"{path}: record {i} is {_json_type(rec)}, expected an object")
    return None


#: A streamed table whose structure looks wrong is parsed whole, to say what it holds instead,
#: up to this size (the error path only).
_DIAGNOSE_MAX_BYTES = 256 * 1024 * 1024


def _diagnosed(path: Path, exc: DataError) -> DataError:
    """A streamed table's structural error, said as what the file holds where it is valid JSON
    of another shape (null, a list of numbers, a list of lists)."""
    try:
        if path.stat().st_size > _DIAGNOSE_MAX_BYTES:
            return exc
        with path.open("rb") as fh:
            data = json.load(fh)
    except (OSError, ValueError):  # not JSON at all (ValueError: decode errors): as it was
        return exc
    return _shape_problem(path, data) or exc


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
    problem = _shape_problem(path, data)
    if problem is not None:
        raise problem
    return data


def _field(path: Path, rec: dict, key: str, i: int | None = None):
    try:
        return rec[key]
    except KeyError:
        where = f"record {rec.get('token', i)!r}"
        raise DataError(f"{path}: {where} has no {key!r} field") from None


def _str_field(path: Path, rec: dict, key: str, i: int | None = None, *, optional: bool = False):
    """``rec[key]`` when it is a string (or None, when ``optional``); DataError otherwise (a
    token that is a number or a list would fail later as a dict key, far from the file)."""
    value = _field(path, rec, key, i)
    if isinstance(value, str) or (optional and value is None):
        return value
    token = rec.get("token")
    where = f"record {token!r}" if isinstance(token, str) else f"record {i}"
    raise DataError(f"{path}: {where} field {key!r} is {value!r}, expected a string")


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
            try:
                _check_structure(path, body, base, started)
            except DataError as exc:
                raise _diagnosed(path, exc) from None
            started = True
            yield body, base
            carry = buf[last + 1 :]
            base += last + 1
        tail = carry.translate(None, _WS)
        if tail != (b"]" if started else b"[]"):
            what = (
                "truncated" if not tail.endswith(b"]") else f"unexpected {tail[:20]!r} at the end"
            )
            raise _diagnosed(path, DataError(f"{path}: corrupt JSON ({what}, after byte {base})"))


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
