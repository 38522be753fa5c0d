"""Consistency checks across the nuScenes tables that do not stop the whole load.

A scene whose samples are broken is recorded per scene (a run that asks for it fails, the others
go on); rotation quaternions that are not unit are normalised with one warning per table.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from radarslam.geometry import quat_norms

log = logging.getLogger("radarslam.nuscenes")


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
