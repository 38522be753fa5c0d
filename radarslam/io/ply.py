"""Point clouds as binary PLY files, laid out as open3d's ``write_point_cloud`` writes them
(double x, y, z; uchar red, green, blue) without importing open3d, which costs about a second
at the end of every run and, cut short by Ctrl-C, fails as an ImportError."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from radarslam.io.atomic import atomic_open


def write_ply_points(path: str | Path, xyz, colors=None) -> None:
    """Write ``xyz`` (N, 3) and optional ``colors`` (N, 3, in [0, 1]; rounded to 8 bits as open3d
    does) to ``path`` atomically."""
    xyz = np.asarray(xyz, dtype=np.float64).reshape(-1, 3)
    fields = [("x", "<f8"), ("y", "<f8"), ("z", "<f8")]
    if colors is not None:
        colors = np.asarray(colors, dtype=np.float64).reshape(-1, 3)
        if len(colors) != len(xyz):
            raise ValueError(f"{len(colors)} colours for {len(xyz)} points")
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    records = np.empty(len(xyz), dtype=fields)
    for k, name in enumerate("xyz"):
        records[name] = xyz[:, k]
    if colors is not None:
        levels = np.floor(np.clip(np.nan_to_num(colors), 0.0, 1.0) * 255.0 + 0.5)
        for k, name in enumerate(("red", "green", "blue")):
            records[name] = levels[:, k]
    kinds = {"<f8": "double", "u1": "uchar"}
    header = [
        "ply",
        "format binary_little_endian 1.0",
        "comment Created by radarslam",
        f"element vertex {len(xyz)}",
        *(f"property {kinds[t]} {name}" for name, t in fields),
        "end_header",
    ]
    with atomic_open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(records.tobytes())
