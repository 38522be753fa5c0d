"""Exact k-nearest-neighbour search over a planar point set, on a uniform grid compiled by numba.

The odometry queries kiss-icp's local map (~20k points, rebuilt every few frames) with a few
hundred points, four times per frame (three refinement steps and the covariance). scipy's
``cKDTree`` answers those queries in tens of microseconds of Python and Cython overhead each and
costs about 2 ms per rebuild; together they were a quarter of the odometry's CPU time. Radar
maps are planar and dense only where the reflectors are, the queries are short-ranged (three
kernel widths, about 2 m), so a grid of 1 m cells sorted once by cell (a counting sort, linear
in the points) answers the same queries exactly: the same neighbours, the same order, the same
squared distances summed in the same order as ``cKDTree`` (``p = 2``, ``eps = 0``).

The output follows ``cKDTree.query``: ``(dist, idx)`` of shape ``(m, k)``, sorted by distance,
``inf`` and ``len(points)`` where fewer than ``k`` neighbours exist (within the bound).
"""

from __future__ import annotations

import math

import numpy as np

from radarslam.errors import ConfigError

#: A grid wider than this many cells gets coarser cells instead (a map of 100 m range needs ~40k).
_MAX_CELLS = 4_000_000


def _njit(fn):
    # numba is imported on first use only: `radarslam --help` and the readers stay fast to load.
    import numba

    return numba.njit(cache=True, nogil=True)(fn)


def _bounds_impl(xy):
    # numpy's min/max over axis 0 of an (n, 2) array walk it with a stride: 7x slower than this
    x0 = y0 = np.inf
    x1 = y1 = -np.inf
    for p in range(xy.shape[0]):
        x = xy[p, 0]
        y = xy[p, 1]
        if not (math.isfinite(x) and math.isfinite(y)):
            return np.nan, np.nan, np.nan, np.nan
        x0 = min(x0, x)
        x1 = max(x1, x)
        y0 = min(y0, y)
        y1 = max(y1, y)
    return x0, y0, x1, y1


def _build_impl(xy, x0, y0, inv_cell, nx, ny):
    n = xy.shape[0]
    cell_of = np.empty(n, dtype=np.int64)
    starts = np.zeros(nx * ny + 1, dtype=np.int64)
    for p in range(n):
        i = math.floor((xy[p, 0] - x0) * inv_cell)
        j = math.floor((xy[p, 1] - y0) * inv_cell)
        i = min(max(i, 0), nx - 1)  # rounding at the far edge of the bounding box
        j = min(max(j, 0), ny - 1)
        c = j * nx + i
        cell_of[p] = c
        starts[c + 1] += 1
    for c in range(nx * ny):
        starts[c + 1] += starts[c]
    fill = starts[:-1].copy()
    order = np.empty(n, dtype=np.int64)
    for p in range(n):  # stable: points of a cell keep their input order
        c = cell_of[p]
        order[fill[c]] = p
        fill[c] += 1
    sx = np.empty(n)
    sy = np.empty(n)
    for q in range(n):
        sx[q] = xy[order[q], 0]
        sy[q] = xy[order[q], 1]
    return order, starts, sx, sy


def _query_impl(
    sx, sy, order, starts, x0, y0, cell, nx, ny, queries, k, bound, need_first_within, n_points
):
    """k nearest per query with squared distance < bound^2 (bound may be inf).

    need_first_within > 0: an unbounded search that gives up (all inf) once it is sure that the
    nearest neighbour lies at or beyond that distance (the caller drops such queries)."""
    m = queries.shape[0]
    dist = np.full((m, k), np.inf)
    idx = np.full((m, k), n_points, dtype=np.int64)
    bound2 = bound * bound
    first2 = need_first_within * need_first_within
    inv_cell = 1.0 / cell
    bd = np.empty(k)
    bi = np.empty(k, dtype=np.int64)
    max_ring = max(nx, ny) + 1
    for q in range(m):
        qx = queries[q, 0]
        qy = queries[q, 1]
        if not (math.isfinite(qx) and math.isfinite(qy)):
            continue
        fi = math.floor((qx - x0) * inv_cell)
        fj = math.floor((qy - y0) * inv_cell)
        # A query far outside the grid: every cell is farther than any ring count we could walk,
        # so start the rings at the grid's nearest cell instead (distances stay exact).
        ci = int(min(max(fi, -1.0), float(nx)))
        cj = int(min(max(fj, -1.0), float(ny)))
        for t in range(k):
            bd[t] = np.inf
            bi[t] = n_points
        found = 0
        ring = 0
        while ring <= max_ring + abs(ci) + abs(cj):
            # Cells of Chebyshev ring `ring` around (ci, cj); each is checked against the current
            # k-th distance (or the bound) by its exact box distance, so the walk stays exact.
            limit2 = bound2
            if found == k and bd[k - 1] < limit2:
                limit2 = bd[k - 1]
            i_lo = ci - ring
            i_hi = ci + ring
            j_lo = cj - ring
            j_hi = cj + ring
            for j in range(max(j_lo, 0), min(j_hi, ny - 1) + 1):
                on_edge_row = j == j_lo or j == j_hi
                if on_edge_row:
                    i_start = max(i_lo, 0)
                    i_step = 1
                else:
                    i_start = i_lo
                    i_step = i_hi - i_lo if ring > 0 else 1
                i = i_start
                while i <= min(i_hi, nx - 1):
                    if i >= 0:
                        # squared distance from the query to the cell's box
                        bx0 = x0 + i * cell
                        by0 = y0 + j * cell
                        dx = 0.0
                        if qx < bx0:
                            dx = bx0 - qx
                        elif qx > bx0 + cell:
                            dx = qx - bx0 - cell
                        dy = 0.0
                        if qy < by0:
                            dy = by0 - qy
                        elif qy > by0 + cell:
                            dy = qy - by0 - cell
                        box2 = dx * dx + dy * dy
                        if box2 < limit2:
                            c = j * nx + i
                            for s in range(starts[c], starts[c + 1]):
                                ex = qx - sx[s]
                                ey = qy - sy[s]
                                d2 = ex * ex + ey * ey
                                if d2 < bound2 and (found < k or d2 < bd[k - 1]):
                                    p = order[s]
                                    # insert, keeping ties in index order (as cKDTree's heap)
                                    t = found if found < k else k - 1
                                    while t > 0 and (
                                        bd[t - 1] > d2 or (bd[t - 1] == d2 and bi[t - 1] > p)
                                    ):
                                        if t < k:
                                            bd[t] = bd[t - 1]
                                            bi[t] = bi[t - 1]
                                        t -= 1
                                    bd[t] = d2
                                    bi[t] = p
                                    if found < k:
                                        found += 1
                                    if found == k and bd[k - 1] < limit2:
                                        limit2 = bd[k - 1]
                    i += i_step
            # The next ring lies at least `ring` cells away from the query's own cell.
            reach = ring * cell
            if need_first_within > 0.0 and reach * reach >= first2:
                if found == 0 or bd[0] >= first2:
                    found = 0
                    break
            if reach * reach >= limit2:
                break
            ring += 1
        for t in range(found):
            dist[q, t] = math.sqrt(bd[t])
            idx[q, t] = bi[t]
    return dist, idx


def _count_impl(sx, sy, starts, x0, y0, cell, nx, ny, queries, radius, stop_at):
    """Points within ``radius`` (distance <= radius, as cKDTree's distances compare), counted up
    to ``stop_at``."""
    m = queries.shape[0]
    counts = np.zeros(m, dtype=np.int64)
    reach = math.ceil(radius / cell)
    inv_cell = 1.0 / cell
    for q in range(m):
        qx = queries[q, 0]
        qy = queries[q, 1]
        if not (math.isfinite(qx) and math.isfinite(qy)):
            continue
        ci = math.floor((qx - x0) * inv_cell)
        cj = math.floor((qy - y0) * inv_cell)
        n = 0
        for j in range(max(cj - reach, 0), min(cj + reach, ny - 1) + 1):
            if n >= stop_at:
                break
            for i in range(max(ci - reach, 0), min(ci + reach, nx - 1) + 1):
                c = j * nx + i
                for s in range(starts[c], starts[c + 1]):
                    ex = qx - sx[s]
                    ey = qy - sy[s]
                    d2 = ex * ex + ey * ey
                    if math.sqrt(d2) <= radius:
                        n += 1
                if n >= stop_at:
                    break
        counts[q] = min(n, stop_at)
    return counts


_kernels: dict[str, object] = {}


def _kernel(name: str):
    fn = _kernels.get(name)
    if fn is None:
        impl = {
            "bounds": _bounds_impl,
            "build": _build_impl,
            "query": _query_impl,
            "count": _count_impl,
        }[name]
        fn = _kernels[name] = _njit(impl)
    return fn


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

    def __len__(self) -> int:
        return self.n

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
            self.sx,
            self.sy,
            self.order,
            self.starts,
            self.x0,
            self.y0,
            self.cell_m,
            self.nx,
            self.ny,
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
        return _kernel("count")(
            self.sx,
            self.sy,
            self.starts,
            self.x0,
            self.y0,
            self.cell_m,
            self.nx,
            self.ny,
            q,
            radius,
            int(stop_at),
        )
