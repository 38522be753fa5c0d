"""Exact k-nearest-neighbour search over a planar point set, on a uniform grid compiled by numba.

The odometry queries kiss-icp's local map (~20k points, rebuilt every few frames) with a few
hundred points, four times per frame (three refinement steps and the covariance). scipy's
``cKDTree`` answers those queries in tens of microseconds of Python and Cython overhead each and
costs about 2 ms per rebuild; together they were a quarter of the odometry's CPU time. Radar
maps are planar and dense only where the reflectors are, the queries are short-ranged (three
kernel widths, about 2 m), so a grid of 1 m cells sorted once by cell (a counting sort, linear
in the points) answers the same queries exactly: the same neighbours, the same order, the same
squared distances summed in the same order as ``cKDTree`` (``p = 2``, ``eps = 0``).

The loop verifier's ICP runs on the same grid (:meth:`GridIndex.icp_point_to_point`, open3d's
point-to-point iterations).

The output follows ``cKDTree.query``: ``(dist, idx)`` of shape ``(m, k)``, sorted by distance,
``inf`` and ``len(points)`` where fewer than ``k`` neighbours exist (within the bound).
"""

from __future__ import annotations

import math

import numpy as np

from radarslam.errors import ConfigError

#: A grid wider than this many cells gets coarser cells instead (a map of 100 m range needs ~40k).
_MAX_CELLS = 4_000_000


def _kernel(name: str):
    # numba is imported on first use only: `radarslam --help` and the readers stay fast to load.
    from radarslam import grid_kernels

    return getattr(grid_kernels, name)


class GridIndex:
    """Planar points indexed for exact k-nearest-neighbour queries (see the module's doc)."""

    def __init__(self, points_xy: np.ndarray, cell_m: float = 1.0):
        if not (isinstance(cell_m, (int, float)) and math.isfinite(cell_m) and cell_m > 0):
            raise ConfigError(f"GridIndex cell_m must be a finite number > 0, got {cell_m!r}")
        xy = np.ascontiguousarray(points_xy, dtype=np.float64)
        if xy.ndim != 2 or xy.shape[1] != 2:
            raise ValueError(f"GridIndex expects (n, 2) points, got shape {xy.shape}")
        self.n = len(xy)
        x0 = y0 = x1 = y1 = 0.0
        if self.n:
            x0, y0, x1, y1 = _kernel("bounds")(xy)
            if not all(math.isfinite(v) for v in (x0, y0, x1, y1)):
                raise ValueError("GridIndex: points contain NaN or inf")
        cell = float(cell_m)
        while True:
            nx = int((x1 - x0) // cell) + 1
            ny = int((y1 - y0) // cell) + 1
            if nx * ny <= _MAX_CELLS:
                break
            cell *= 2.0
        self.cell_m, self.x0, self.y0, self.nx, self.ny = cell, x0, y0, nx, ny
        self.order, self.starts, self.sx, self.sy = _kernel("build")(xy, x0, y0, 1.0 / cell, nx, ny)
        # The arguments every kernel takes first, in this order.
        self._grid = (self.sx, self.sy, self.order, self.starts, x0, y0, cell, nx, ny)

    def __len__(self) -> int:
        return self.n

    @property
    def kernel_arguments(
        self,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, float, float, float, int, int]:
        """The sorted points and grid geometry every kernel of :mod:`radarslam.grid_kernels`
        takes first (``sx, sy, order, starts, x0, y0, cell, nx, ny``): for compiled code that
        queries the index itself."""
        return self._grid

    def query(
        self,
        points_xy: np.ndarray,
        k: int,
        distance_upper_bound: float = math.inf,
        *,
        nearest_within: float | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """``cKDTree.query(points, k, distance_upper_bound=...)`` for ``k >= 1`` (2-D output).

        ``nearest_within``: rows whose nearest neighbour is not closer than this come back empty
        (``inf`` / ``n``) without the unbounded search finishing them; the others are exact."""
        q = np.ascontiguousarray(points_xy, dtype=np.float64)
        if q.ndim != 2 or q.shape[1] != 2:
            raise ValueError(f"GridIndex.query expects (m, 2) points, got shape {q.shape}")
        if int(k) < 1:
            raise ValueError(f"GridIndex.query: k must be >= 1, got {k!r}")
        bound = float(distance_upper_bound)
        first = 0.0 if nearest_within is None else float(nearest_within)
        if self.n == 0:
            return np.full((len(q), int(k)), np.inf), np.full((len(q), int(k)), 0, dtype=np.int64)
        return _kernel("query")(
            *self._grid,
            q,
            int(k),
            bound,
            first,
            self.n,
        )

    def count_within(self, points_xy: np.ndarray, radius_m: float, stop_at: int) -> np.ndarray:
        """Per query, the indexed points at distance <= ``radius_m`` (a query point that is
        itself indexed counts itself), counted up to ``stop_at``: ``(m,)`` int64."""
        q = np.ascontiguousarray(points_xy, dtype=np.float64)
        if q.ndim != 2 or q.shape[1] != 2:
            raise ValueError(f"GridIndex.count_within expects (m, 2) points, got shape {q.shape}")
        radius = float(radius_m)
        if not (math.isfinite(radius) and radius >= 0):
            raise ValueError(
                f"GridIndex.count_within: radius_m must be finite and >= 0, got {radius_m!r}"
            )
        if self.n == 0 or int(stop_at) < 1:
            return np.zeros(len(q), dtype=np.int64)
        return _kernel("count")(*self._grid, q, radius, int(stop_at))

    def icp_point_to_point(
        self,
        source_xy: np.ndarray,
        init: np.ndarray,
        max_correspondence_m: float,
        relative_fitness: float,
        relative_rmse: float,
        max_iterations: int,
    ) -> np.ndarray:
        """Planar point-to-point ICP of ``source_xy`` onto the indexed points from ``init`` (4x4,
        its planar part used), the iterations of open3d's ``registration_icp`` with
        ``TransformationEstimationPointToPoint`` and the same convergence test; returns the 4x4
        ``target_from_source``. One thread, no copies into open3d's clouds and trees."""
        src = np.ascontiguousarray(source_xy, dtype=np.float64)
        if src.ndim != 2 or src.shape[1] != 2:
            raise ValueError(f"GridIndex.icp_point_to_point expects (n, 2) points, got {src.shape}")
        pose = np.asarray(init, dtype=np.float64)
        planar = np.array([[*pose[0, :2], pose[0, 3]], [*pose[1, :2], pose[1, 3]], [0.0, 0.0, 1.0]])
        out = np.eye(4)
        if self.n == 0 or len(src) == 0:
            out[:2, :2], out[:2, 3] = planar[:2, :2], planar[:2, 2]
            return out
        t = _kernel("icp_point_to_point")(
            src,
            *self._grid,
            planar,
            float(max_correspondence_m),
            float(relative_fitness),
            float(relative_rmse),
            int(max_iterations),
        )
        out[:2, :2], out[:2, 3] = t[:2, :2], t[:2, 2]
        return out
