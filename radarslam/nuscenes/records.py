"""The compact in-memory form of the nuScenes tables: sorted-token lookup and the radar rows.

:class:`RadarIndex` holds every radar ``sample_data`` record of a version as numpy columns and
:class:`SmallTables` the small tables; :class:`TokenIndex` finds tokens through a sorted array
(32 bytes a record, not a dict entry).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np

from radarslam.errors import DataError


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
