"""Per-point radar filters on the nuScenes state fields, as explicit values (never global state).

The devkit keeps its filter settings as class-level globals of ``RadarPointCloud`` that every later
call silently inherits; here a filter is a frozen value passed to the reader.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from radarslam.errors import ConfigError


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
        return cls(invalid_states={0}, dynprop_states=range(7), ambig_states={3})

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

    def mask(self, points: np.ndarray) -> np.ndarray:
        """Boolean mask of the points (structured, RADAR_DTYPE fields) that pass the filter."""
        keep = np.ones(len(points), dtype=bool)
        for field, allowed in (
            ("invalid_state", self.invalid_states),
            ("dyn_prop", self.dynprop_states),
            ("ambig_state", self.ambig_states),
        ):
            if allowed is not None:
                keep &= np.isin(
                    points[field], np.fromiter(allowed, dtype=np.int64, count=len(allowed))
                )
        return keep

    def apply(self, points: np.ndarray) -> np.ndarray:
        """The points that pass (a copy only when something is removed)."""
        if self.is_noop:
            return points
        keep = self.mask(points)
        return points if keep.all() else points[keep]

    def describe(self) -> str:
        def fmt(s):
            return "any" if s is None else "{" + ",".join(str(v) for v in sorted(s)) + "}"

        return (
            f"invalid_state in {fmt(self.invalid_states)}, dyn_prop in {fmt(self.dynprop_states)}, "
            f"ambig_state in {fmt(self.ambig_states)}"
        )
