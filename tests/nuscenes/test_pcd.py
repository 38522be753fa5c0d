"""The radar .pcd codec on hand-made bytes: padding, field order, and every malformed header."""

from __future__ import annotations

import numpy as np
import pytest

from radarslam.errors import DataError
from radarslam.nuscenes.pcd import parse_pcd_bytes, pcd_bytes, read_pcd, write_pcd
from radarslam.types import RADAR_DTYPE, RADAR_FIELDS

SIZES = "4 4 4 1 2 4 4 4 4 4 1 1 1 1 1 1 1 1".split()
TYPES = "F F F I I F F F F F I I I I I I I I".split()


def make_points(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pts = np.zeros(n, dtype=RADAR_DTYPE)
    for name in RADAR_FIELDS:
        if RADAR_DTYPE[name].kind == "f":
            pts[name] = rng.normal(0, 30, n)
        else:
            pts[name] = rng.integers(0, 18, n)
    pts["z"] = 0
    return pts


def header(n: int, fields=RADAR_FIELDS, sizes=SIZES, types=TYPES, data="binary", **over) -> bytes:
    lines = {
        "#": "# .PCD v0.7 - Point Cloud Data file format",
        "VERSION": "VERSION 0.7",
        "FIELDS": "FIELDS " + " ".join(fields),
        "SIZE": "SIZE " + " ".join(sizes),
        "TYPE": "TYPE " + " ".join(types),
        "COUNT": "COUNT " + " ".join(["1"] * len(fields)),
        "WIDTH": f"WIDTH {n}",
        "HEIGHT": "HEIGHT 1",
        "VIEWPOINT": "VIEWPOINT 0 0 0 1 0 0 0",
        "POINTS": f"POINTS {n}",
        "DATA": f"DATA {data}",
    }
    lines.update(over)
    return ("\n".join(v for v in lines.values() if v is not None) + "\n").encode("ascii")


@pytest.mark.parametrize("padding", [0, 1, 4096])
def test_roundtrip_with_and_without_padding(padding):
    pts = make_points(125)
    data = pcd_bytes(pts, padding=padding)
    assert len(data) == len(header(125)) + 125 * 43 + padding
    out = parse_pcd_bytes(data)
    assert out.dtype == RADAR_DTYPE
    assert out.tobytes() == pts.tobytes()


def test_hand_made_header_matches_writer():
    pts = make_points(3)
    assert header(3) + pts.tobytes() == pcd_bytes(pts)


def test_fields_in_another_order():
    pts = make_points(40, seed=1)
    order = list(reversed(range(len(RADAR_FIELDS))))
    fields = [RADAR_FIELDS[i] for i in order]
    dt = np.dtype([(f, RADAR_DTYPE[f]) for f in fields])
    shuffled = np.zeros(len(pts), dtype=dt)
    for f in fields:
        shuffled[f] = pts[f]
    data = header(
        40, fields=fields, sizes=[SIZES[i] for i in order], types=[TYPES[i] for i in order]
    )
    out = parse_pcd_bytes(data + shuffled.tobytes() + b"\0" * 7)
    assert out.dtype == RADAR_DTYPE
    assert out.tobytes() == pts.tobytes()


def test_zero_points():
    out = parse_pcd_bytes(header(0))
    assert len(out) == 0 and out.dtype == RADAR_DTYPE


def test_file_roundtrip_and_missing(tmp_path):
    pts = make_points(5)
    write_pcd(tmp_path / "a.pcd", pts)
    assert read_pcd(tmp_path / "a.pcd").tobytes() == pts.tobytes()
    with pytest.raises(DataError, match=r"b\.pcd: radar file is missing"):
        read_pcd(tmp_path / "b.pcd")
    with pytest.raises(DataError, match="is a directory"):
        read_pcd(tmp_path)


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (header(10) + make_points(10).tobytes()[:-1], "truncated: header says 10 points"),
        (header(10), "truncated"),
        (header(10)[:60], "truncated header"),
        (header(3, POINTS="POINTS three") + make_points(3).tobytes(), "POINTS .* not an integer"),
        (header(3, POINTS="POINTS -3"), "negative POINTS"),
        (header(3, WIDTH="WIDTH 4") + make_points(3).tobytes(), "WIDTH\\*HEIGHT = 4"),
        (header(3, FIELDS=None) + make_points(3).tobytes(), "no FIELDS line"),
        (header(3, data="ascii") + b"1 2 3\n", "DATA ascii is not supported"),
        (header(3, data="binary_compressed"), "DATA binary_compressed is not supported"),
        (header(3, sizes=["8", *SIZES[1:]]) + make_points(3).tobytes(), "'x' is SIZE 8 TYPE F"),
        (header(3, types=["I", *TYPES[1:]]) + make_points(3).tobytes(), "'x' is SIZE 4 TYPE I"),
        (header(3, sizes=["four", *SIZES[1:]]), "SIZE 'four', not an integer"),
        (header(3, sizes=SIZES[:-1]), "different lengths"),
        (header(3, fields=["x", *RADAR_FIELDS[1:-1], "intensity"]), "unexpected field 'intensity'"),
        (header(3, fields=["x", "x", *RADAR_FIELDS[2:]]), "repeats x"),
        (header(3, COUNT="COUNT " + " ".join(["2"] + ["1"] * 17)), "COUNT 2"),
        (
            header(3, fields=RADAR_FIELDS[:-1], sizes=SIZES[:-1], types=TYPES[:-1]),
            "lacks radar field",
        ),
        (b"\xff\xfe garbage\n" * 3, "not ASCII"),
        (b"# comment\n" + b"VERSION 0.7\n" * 70, "no 'DATA' line"),
        (header(3).replace(b"DATA binary\n", b"") + b"\xff\xfe\x01\n" * 8, "no 'DATA' line before"),
    ],
)
def test_malformed(data, match):
    with pytest.raises(DataError, match=match):
        parse_pcd_bytes(data, "bad.pcd")


def test_error_names_the_file(tmp_path):
    p = tmp_path / "RADAR_FRONT__123.pcd"
    p.write_bytes(header(10) + b"\0" * 100)
    with pytest.raises(DataError) as exc:
        read_pcd(p)
    msg = str(exc.value)
    assert msg.startswith(str(p)) and "\n" not in msg


def test_a_header_seen_before_still_checks_its_file():
    """Headers are parsed once per distinct header; the next file with the same header must still
    be read in full and still fail when it is truncated."""
    a, b = make_points(7, seed=1), make_points(7, seed=2)
    assert parse_pcd_bytes(header(7) + a.tobytes() + b"\0").tobytes() == a.tobytes()
    assert parse_pcd_bytes(header(7) + b.tobytes() + b"\0").tobytes() == b.tobytes()
    with pytest.raises(DataError, match="truncated: header says 7 points"):
        parse_pcd_bytes(header(7) + b.tobytes()[:-3], "c.pcd")
    # a header that failed is never remembered: it fails again
    bad = header(7, sizes=["8", *SIZES[1:]]) + a.tobytes()
    for _ in range(2):
        with pytest.raises(DataError, match="'x' is SIZE 8"):
            parse_pcd_bytes(bad)
