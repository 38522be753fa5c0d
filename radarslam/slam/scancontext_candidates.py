"""Rotation-invariant loop candidates (ScanContext) for revisits driven the other way round.

AutoPlace's radar image is drawn in the vehicle's frame, so the same street driven in the
opposite direction gives a different image (rotated, and seen from the other side of every
reflector), and its descriptor never ranks the earlier pass among the candidates: a session that
only ever drives the map's streets the other way stays unlinked. ScanContext (Kim & Kim 2018, the
baseline of the place-recognition benchmark) compares polar grids under every column shift, i.e.
every heading, so it proposes those places. On its own it is a weak detector (on the demo city its
best candidate is a true revisit for 11 of 20 reversed key frames, and its distance does not tell
which), so its candidates only go to the global registration search over headings, and a session
is linked only when several such loops agree (``link_min_consistent_loops``).

:class:`ScanContextCandidates` is a database of key frames: ``add(key, xy)`` stores one,
``query(xy, allowed, k)`` is pure and ranks the stored key frames that ``allowed`` admits.
"""

from __future__ import annotations

from collections.abc import Callable, Hashable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ScanContextCandidate:
    key: Hashable
    distance: float  # column-shift cosine distance, 0 (same) .. 1
    shift_deg: float  # heading change that best aligns the query with the candidate


class ScanContextCandidates:
    """ScanContext database of key-frame clouds (points in the key frame's ego frame, (N, 2))."""

    def __init__(self, ring_candidates: int = 25, config=None):
        from radarslam.place_recognition.config import ScanContextConfig

        self.config = config or ScanContextConfig()
        self.ring_candidates = ring_candidates
        rings, sectors = self.config.num_rings, self.config.num_sectors
        self._contexts = np.zeros((64, rings, sectors), np.float32)  # grown by doubling
        self._rings = np.zeros((64, rings), np.float32)
        self._keys: list[Hashable] = []

    def __len__(self) -> int:
        return len(self._keys)

    def describe(self, xy: np.ndarray) -> np.ndarray:
        from radarslam.place_recognition.baselines.scancontext import scan_context

        return scan_context(np.asarray(xy, dtype=np.float64)[:, :2], self.config)

    def add(self, key: Hashable, xy: np.ndarray, context: np.ndarray | None = None) -> None:
        from radarslam.place_recognition.baselines.scancontext import ring_key

        sc = self.describe(xy) if context is None else context
        n = len(self._keys)
        if n == len(self._contexts):
            self._contexts = np.concatenate([self._contexts, np.zeros_like(self._contexts)])
            self._rings = np.concatenate([self._rings, np.zeros_like(self._rings)])
        self._contexts[n] = sc
        self._rings[n] = ring_key(sc)
        self._keys.append(key)

    def query(
        self,
        xy: np.ndarray,
        allowed: Callable[[Hashable], bool],
        k: int = 1,
        context: np.ndarray | None = None,
    ) -> list[ScanContextCandidate]:
        """The ``k`` best stored key frames that ``allowed`` admits: ring-key nearest neighbours
        (rotation invariant), re-ranked by the column-shift distance."""
        from radarslam.place_recognition.baselines.scancontext import ring_key, shift_distance

        n = len(self._keys)
        ok = np.fromiter((allowed(key) for key in self._keys), dtype=bool, count=n)
        rows = np.flatnonzero(ok)
        if not len(rows):
            return []
        sc = self.describe(xy) if context is None else context
        if not np.any(sc):
            return []
        d_ring = np.linalg.norm(self._rings[rows] - ring_key(sc), axis=1)
        near = rows[np.argsort(d_ring, kind="stable")[: self.ring_candidates]]
        dist, shift = shift_distance(sc, self._contexts[near])
        order = np.argsort(dist, kind="stable")[:k]
        step = 360.0 / self.config.num_sectors
        return [
            ScanContextCandidate(self._keys[near[i]], float(dist[i]), float(shift[i] * step))
            for i in order
        ]
