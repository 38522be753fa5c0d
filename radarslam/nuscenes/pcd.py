"""The nuScenes radar ``.pcd`` format: a header-driven binary reader and a writer.

The reader parses the ASCII header (whatever its field order, as long as each field is one of the
18 radar fields with the right size and type), reads ``POINTS`` records and ignores the trailing
padding that real files carry. It never trusts the file size for the point count.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from radarslam.errors import DataError
from radarslam.types import RADAR_DTYPE, RADAR_FIELDS

_SIZE_TYPE = {name: (RADAR_DTYPE[name].itemsize, RADAR_DTYPE[name].kind) for name in RADAR_FIELDS}
_PCD_KIND = {"f": "F", "i": "I", "u": "U"}
_MAX_HEADER_LINES = 64


_DTYPE_CACHE: dict[tuple, np.dtype] = {}


def _header_dtype(path: str | Path, header: dict[str, list[str]]) -> np.dtype:
    fields = header["FIELDS"]
    sizes, types = header["SIZE"], header["TYPE"]
    counts = header.get("COUNT", ["1"] * len(fields))
    key = (tuple(fields), tuple(sizes), tuple(types), tuple(counts))
    dtype = _DTYPE_CACHE.get(key)
    if dtype is None:  # only valid headers are cached; a bad one raises every time
        dtype = _DTYPE_CACHE[key] = _build_dtype(path, fields, sizes, types, counts)
    return dtype


def _build_dtype(path: str | Path, fields, sizes, types, counts) -> np.dtype:
    if not (len(fields) == len(sizes) == len(types) == len(counts)):
        raise DataError(f"{path}: header FIELDS/SIZE/TYPE/COUNT have different lengths")
    dup = sorted({f for f in fields if fields.count(f) > 1})
    if dup:
        raise DataError(f"{path}: header FIELDS repeats {', '.join(dup)}")
    parts = []
    for name, size, kind, count in zip(fields, sizes, types, counts, strict=True):
        if count != "1":
            raise DataError(f"{path}: field {name!r} has COUNT {count}; radar fields have COUNT 1")
        if not size.isdigit():
            raise DataError(f"{path}: field {name!r} has SIZE {size!r}, not an integer")
        if name in _SIZE_TYPE:
            want_size, want_kind = _SIZE_TYPE[name]
            if int(size) != want_size or kind != _PCD_KIND[want_kind]:
                raise DataError(
                    f"{path}: field {name!r} is SIZE {size} TYPE {kind}, "
                    f"expected SIZE {want_size} TYPE {_PCD_KIND[want_kind]}"
                )
            parts.append((name, RADAR_DTYPE[name]))
        else:
            raise DataError(f"{path}: unexpected field {name!r} in header (not a radar .pcd?)")
    missing = [f for f in RADAR_FIELDS if f not in fields]
    if missing:
        raise DataError(f"{path}: header lacks radar field(s) {', '.join(missing)}")
    return np.dtype(parts)


#: Headers already parsed and validated (exact bytes up to and including the DATA line) ->
#: (dtype, POINTS). A dataset's files share a few hundred headers (they differ only in the point
#: count), so most files skip the header parse (a third of the reading time).
_HEADER_CACHE: dict[bytes, tuple[np.dtype, int]] = {}
_HEADER_CACHE_MAX = 65536
_DATA_LINE = b"\nDATA binary\n"


def _records(data: bytes, pos: int, n: int, dtype: np.dtype, path) -> np.ndarray:
    need = n * dtype.itemsize
    if len(data) - pos < need:
        raise DataError(
            f"{path}: truncated: header says {n} points ({need} bytes) "
            f"but only {len(data) - pos} bytes follow the header"
        )
    if dtype == RADAR_DTYPE:
        # a bytearray copy is a plain memcpy; ndarray.copy() of this packed 18-field dtype walks
        # the fields and is ~10x slower
        return np.frombuffer(bytearray(data[pos : pos + need]), dtype=RADAR_DTYPE, count=n)
    records = np.frombuffer(data, dtype=dtype, count=n, offset=pos)
    out = np.empty(n, dtype=RADAR_DTYPE)
    for name in RADAR_FIELDS:
        out[name] = records[name]
    return out


def parse_pcd_bytes(data: bytes, path: str | Path = "<bytes>") -> np.ndarray:
    """Parse a radar .pcd from memory into a structured array of :data:`RADAR_DTYPE`."""
    end = data.find(_DATA_LINE, 0, 8192)
    if end >= 0:
        pos = end + len(_DATA_LINE)
        known = _HEADER_CACHE.get(data[:pos])
        if known is not None:
            return _records(data, pos, known[1], known[0], path)
    header: dict[str, list[str]] = {}
    pos = 0
    for _ in range(_MAX_HEADER_LINES):
        end = data.find(b"\n", pos)
        if end < 0:
            raise DataError(f"{path}: truncated header (no 'DATA' line)")
        try:
            line = data[pos:end].decode("ascii").strip()
        except UnicodeDecodeError:
            if header:  # header lines were read, then binary data without a DATA line
                raise DataError(f"{path}: header has no 'DATA' line before its data") from None
            raise DataError(f"{path}: header is not ASCII (not a .pcd file?)") from None
        pos = end + 1
        if not line or line.startswith("#"):
            continue
        key, *values = line.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            break
    else:
        raise DataError(f"{path}: no 'DATA' line in the first {_MAX_HEADER_LINES} header lines")
    for key in ("FIELDS", "SIZE", "TYPE", "POINTS", "DATA"):
        if key not in header:
            raise DataError(f"{path}: header has no {key} line")
    if header["DATA"] != ["binary"]:
        raise DataError(f"{path}: DATA {' '.join(header['DATA'])} is not supported (need binary)")
    try:
        n = int(header["POINTS"][0])
    except (ValueError, IndexError):
        raise DataError(f"{path}: POINTS {header['POINTS']} is not an integer") from None
    if n < 0:
        raise DataError(f"{path}: negative POINTS {n}")
    if "WIDTH" in header and "HEIGHT" in header:
        try:
            w, h = int(header["WIDTH"][0]), int(header["HEIGHT"][0])
        except (ValueError, IndexError):
            raise DataError(f"{path}: WIDTH/HEIGHT are not integers") from None
        if w * h != n:
            raise DataError(f"{path}: WIDTH*HEIGHT = {w * h} disagrees with POINTS {n}")
    dtype = _header_dtype(path, header)
    out = _records(data, pos, n, dtype, path)
    if data[pos - len(_DATA_LINE) : pos] == _DATA_LINE:  # the form the fast path looks for
        if len(_HEADER_CACHE) >= _HEADER_CACHE_MAX:
            _HEADER_CACHE.clear()
        _HEADER_CACHE[data[:pos]] = (dtype, n)
    return out


def read_pcd(path: str | Path) -> np.ndarray:
    """Read a radar ``.pcd`` file into a structured array of :data:`RADAR_DTYPE` (all points)."""
    try:
        with open(path, "rb") as f:  # not Path.read_bytes: path parsing costs as much as the read
            data = f.read()
    except FileNotFoundError:
        raise DataError(f"{path}: radar file is missing") from None
    except IsADirectoryError:
        raise DataError(f"{path}: is a directory, expected a radar .pcd file") from None
    except OSError as exc:
        raise DataError(f"{path}: cannot read radar file ({exc.strerror})") from None
    return parse_pcd_bytes(data, path)


def pcd_bytes(points: np.ndarray, padding: int = 0) -> bytes:
    """Encode points (:data:`RADAR_DTYPE` or a compatible structured array) as a radar .pcd.

    ``padding`` zero bytes follow the records, as in real files (the devkit's reader needs at least
    one byte after the records).
    """
    pts = np.asarray(points)
    if pts.dtype != RADAR_DTYPE:
        converted = np.zeros(len(pts), dtype=RADAR_DTYPE)
        for name in RADAR_FIELDS:
            converted[name] = pts[name]
        pts = converted
    n = len(pts)
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\n"
        "VERSION 0.7\n"
        f"FIELDS {' '.join(RADAR_FIELDS)}\n"
        "SIZE 4 4 4 1 2 4 4 4 4 4 1 1 1 1 1 1 1 1\n"
        "TYPE F F F I I F F F F F I I I I I I I I\n"
        "COUNT 1 1 1 1 1 1 1 1 1 1 1 1 1 1 1 1 1 1\n"
        f"WIDTH {n}\n"
        "HEIGHT 1\n"
        "VIEWPOINT 0 0 0 1 0 0 0\n"
        f"POINTS {n}\n"
        "DATA binary\n"
    )
    return header.encode("ascii") + pts.tobytes() + b"\x00" * padding


def write_pcd(path: str | Path, points: np.ndarray, padding: int = 1) -> None:
    """Write a radar .pcd atomically (temporary file + rename)."""
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp{os.getpid()}")
    tmp.write_bytes(pcd_bytes(points, padding=padding))
    os.replace(tmp, path)
