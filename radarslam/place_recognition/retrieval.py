"""Nearest-neighbour search over global descriptors.

Exact Euclidean search in numpy (blocked matrix products); faiss ``IndexFlatL2`` (also exact) is
imported lazily when the database is large or when asked for. Distances are plain (not squared) L2,
as the reference's sklearn kNN that feeds RCSHR.
"""

from __future__ import annotations

import numbers
from dataclasses import dataclass
from typing import Any

import numpy as np

from radarslam.errors import ConfigError, DataError
from radarslam.place_recognition.config import RetrievalConfig


@dataclass(frozen=True)
class SearchResult:
    indices: np.ndarray  # (Q, K) int64 row indices into the database, best first
    distances: np.ndarray  # (Q, K) float64 Euclidean distances (ascending)


def _as_matrix(x: np.ndarray, what: str) -> np.ndarray:
    x = np.asarray(x)
    if x.ndim != 2:
        raise DataError(f"{what} must be a 2-D (N, D) array, got shape {x.shape}")
    x = x.astype(np.float32, copy=False)
    if x.size and not np.all(np.isfinite(x)):
        raise DataError(f"{what} contain NaN or infinity")
    return x


def check_k(k, what: str = "k") -> int:
    """``k`` as an int; anything but an integer >= 1 (bool excluded) is a DataError naming it."""
    if isinstance(k, (bool, np.bool_)) or not isinstance(k, numbers.Integral):
        raise DataError(f"{what} must be an integer >= 1, got {k!r} ({type(k).__name__})")
    if k < 1:
        raise DataError(f"{what} must be an integer >= 1, got {k}")
    return int(k)


class DescriptorIndex:
    """Exact L2 index. ``add`` appends rows; ``search`` never mutates the index."""

    def __init__(self, dim: int, cfg: RetrievalConfig | None = None):
        if dim < 1:
            raise ConfigError(f"descriptor dimension must be >= 1, got {dim}")
        self.dim = int(dim)
        self.cfg = cfg or RetrievalConfig()
        self._chunks: list[np.ndarray] = []
        self._matrix: np.ndarray | None = None  # concatenation of _chunks, built on demand
        self._faiss: Any = None  # a faiss.IndexFlatL2, built on demand

    @classmethod
    def from_descriptors(
        cls, db: np.ndarray, cfg: RetrievalConfig | None = None
    ) -> DescriptorIndex:
        db = _as_matrix(db, "database descriptors")
        index = cls(db.shape[1], cfg)
        index.add(db)
        return index

    def __len__(self) -> int:
        return sum(len(c) for c in self._chunks)

    @property
    def matrix(self) -> np.ndarray:
        """The (N, D) float32 database, as a read-only view (no copy: a database can be large,
        and writing into it would silently change later searches)."""
        view = self._full().view()
        view.setflags(write=False)
        return view

    def _full(self) -> np.ndarray:
        if self._matrix is None:
            if self._chunks:
                self._matrix = np.concatenate(self._chunks)
                self._chunks = [self._matrix]
            else:
                self._matrix = np.zeros((0, self.dim), np.float32)
            # the array itself is read-only too, so that no view of it can be made writable
            self._matrix.setflags(write=False)
        return self._matrix

    def add(self, descriptors: np.ndarray) -> None:
        d = _as_matrix(np.atleast_2d(descriptors), "descriptors")
        if d.shape[1] != self.dim:
            raise DataError(f"descriptor dimension {d.shape[1]} != index dimension {self.dim}")
        self._chunks.append(np.array(d, dtype=np.float32, copy=True))
        self._matrix = None
        self._faiss = None

    def _use_faiss(self) -> bool:
        if self.cfg.backend == "numpy":
            return False
        if self.cfg.backend == "faiss":
            return True
        if len(self) < self.cfg.faiss_min_database:
            return False
        try:
            import faiss  # noqa: F401
        except ImportError:
            return False
        return True

    def search(self, queries: np.ndarray, k: int) -> SearchResult:
        q = _as_matrix(np.atleast_2d(queries), "query descriptors")
        if q.shape[1] != self.dim:
            raise DataError(f"query dimension {q.shape[1]} != index dimension {self.dim}")
        k = min(check_k(k), len(self))
        if k == 0:
            return SearchResult(np.zeros((len(q), 0), np.int64), np.zeros((len(q), 0)))
        if self._use_faiss():
            return self._search_faiss(q, k)
        return self._search_numpy(q, k)

    def _search_numpy(self, q: np.ndarray, k: int) -> SearchResult:
        db = self._full()
        db_sq = np.einsum("ij,ij->i", db, db, dtype=np.float64)
        out_i = np.empty((len(q), k), np.int64)
        out_d = np.empty((len(q), k), np.float64)
        for s in range(0, len(q), self.cfg.chunk_size):
            block = q[s : s + self.cfg.chunk_size]
            q_sq = np.einsum("ij,ij->i", block, block, dtype=np.float64)
            d2 = q_sq[:, None] + db_sq[None, :] - 2.0 * (block.astype(np.float64) @ db.T)
            np.maximum(d2, 0.0, out=d2)
            if k < d2.shape[1]:
                part = np.argpartition(d2, k - 1, axis=1)[:, :k]
            else:
                part = np.broadcast_to(np.arange(d2.shape[1]), d2.shape).copy()
            vals = np.take_along_axis(d2, part, axis=1)
            # lexsort keeps ties in database order, so results are deterministic
            order = np.lexsort((part, vals), axis=1)
            out_i[s : s + len(block)] = np.take_along_axis(part, order, axis=1)
            out_d[s : s + len(block)] = np.sqrt(np.take_along_axis(vals, order, axis=1))
        return SearchResult(out_i, out_d)

    def _search_faiss(self, q: np.ndarray, k: int) -> SearchResult:
        try:
            import faiss
        except ImportError:
            raise ConfigError("retrieval.backend='faiss' but faiss-cpu is not installed") from None
        if self._faiss is None:
            index = faiss.IndexFlatL2(self.dim)
            index.add(np.ascontiguousarray(self._full(), dtype=np.float32))
            self._faiss = index
        d2, idx = self._faiss.search(np.ascontiguousarray(q, dtype=np.float32), k)
        return SearchResult(idx.astype(np.int64), np.sqrt(np.maximum(d2, 0.0)).astype(np.float64))
