"""Per-point radar filters on the nuScenes state fields, as explicit values (never global state).

The devkit keeps its filter settings as class-level globals of ``RadarPointCloud`` that every later
call silently inherits; here a filter is a frozen value passed to the reader.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from radarslam.errors import ConfigError
from radarslam.types import RADAR_DTYPE


def _states(name: str, values: Iterable[int] | None) -> frozenset[int] | None:
    if values is None:
        return None
    if isinstance(values, (str, bytes)):
        raise ConfigError(f"RadarPointFilter.{name}: expected integers, got {values!r}")
    out = set()
    for v in values:
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)):
            raise ConfigError(f"RadarPointFilter.{name}: {v!r} is not an integer state")
        if not -128 <= int(v) <= 127:
            raise ConfigError(f"RadarPointFilter.{name}: state {v} does not fit the int8 field")
        out.add(int(v))
    return frozenset(out)


_OFFSET = {name: field[1] for name, field in (RADAR_DTYPE.fields or {}).items()}


def _bytes_view(points: np.ndarray) -> np.ndarray | None:
    """(N, 43) uint8 view of contiguous RADAR_DTYPE records, else None."""
    if points.dtype != RADAR_DTYPE or not points.flags.c_contiguous or points.ndim != 1:
        return None
    return points.view(np.uint8).reshape(len(points), RADAR_DTYPE.itemsize)


@dataclass(frozen=True)
class RadarPointFilter:
    """Which values of ``invalid_state``, ``dyn_prop`` and ``ambig_state`` a point may have.

    Each field is a set of allowed values, or None for "no filter on that field". The set order
    and duplicates do not matter (any iterable of ints is accepted and frozen).
    """

    invalid_states: frozenset[int] | None = None
    dynprop_states: frozenset[int] | None = None
    ambig_states: frozenset[int] | None = None

    def __post_init__(self) -> None:
        for name in ("invalid_states", "dynprop_states", "ambig_states"):
            object.__setattr__(self, name, _states(name, getattr(self, name)))

    @classmethod
    def devkit_default(cls) -> RadarPointFilter:
        """The devkit defaults: invalid_state 0, dyn_prop 0..6 (drops 7 stopped), ambig_state 3."""
        return cls(
            invalid_states=frozenset({0}),
            dynprop_states=frozenset(range(7)),
            ambig_states=frozenset({3}),
        )

    @classmethod
    def none(cls) -> RadarPointFilter:
        """Keep every point."""
        return cls()

    @property
    def is_noop(self) -> bool:
        return (
            self.invalid_states is None
            and self.dynprop_states is None
            and self.ambig_states is None
        )

    @cached_property
    def _tables(self) -> tuple[tuple[str, np.ndarray], ...]:
        # 256-entry lookup tables indexed by the state byte (int8 read as uint8): one gather per
        # field instead of np.isin, several times faster on 125-point sweeps
        out = []
        for field_name, allowed in (
            ("invalid_state", self.invalid_states),
            ("dyn_prop", self.dynprop_states),
            ("ambig_state", self.ambig_states),
        ):
            if allowed is not None:
                lut = np.zeros(256, dtype=bool)
                lut[np.fromiter(allowed, dtype=np.int64, count=len(allowed)) & 0xFF] = True
                out.append((field_name, lut))
        return tuple(out)

    def mask(self, points: np.ndarray) -> np.ndarray:
        """Boolean mask of the points (structured, RADAR_DTYPE fields) that pass the filter."""
        keep = np.ones(len(points), dtype=bool)
        raw = _bytes_view(points)
        for field_name, lut in self._tables:
            if raw is not None:
                keep &= lut[raw[:, _OFFSET[field_name]]]
            else:
                keep &= lut[points[field_name].astype(np.uint8)]
        return keep

    def apply(self, points: np.ndarray) -> np.ndarray:
        """The points that pass (a copy only when something is removed)."""
        if self.is_noop:
            return points
        keep = self.mask(points)
        if keep.all():
            return points
        raw = _bytes_view(points)
        if raw is None:
            return points[keep]
        # row gather on the byte view: a memcpy per record instead of a per-field copy
        return raw[keep].view(RADAR_DTYPE).reshape(-1)

    def describe(self) -> str:
        def fmt(s):
            return "any" if s is None else "{" + ",".join(str(v) for v in sorted(s)) + "}"

        return (
            f"invalid_state in {fmt(self.invalid_states)}, dyn_prop in {fmt(self.dynprop_states)}, "
            f"ambig_state in {fmt(self.ambig_states)}"
        )
