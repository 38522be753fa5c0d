"""numba kernels of :mod:`radarslam.neighbors` (the grid index) and of the loop verifier's ICP.

Imported only where they are used, so that loading the package does not load numba."""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def bounds(xy):
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


@numba.njit(cache=True, nogil=True)
def build(xy, x0, y0, inv_cell, nx, ny):
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


@numba.njit(cache=True, nogil=True)
def _gap(q, lo, cell):
    """Distance from q to the interval [lo, lo + cell] (0 inside)."""
    if q < lo:
        return lo - q
    if q > lo + cell:
        return q - lo - cell
    return 0.0


@numba.njit(cache=True, nogil=True)
def query(
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
                        dx = _gap(qx, x0 + i * cell, cell)
                        dy = _gap(qy, y0 + j * cell, cell)
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


@numba.njit(cache=True, nogil=True)
def count(sx, sy, order, starts, x0, y0, cell, nx, ny, queries, radius, stop_at):
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


@numba.njit(cache=True, nogil=True)
def _scan_cell(sx, sy, order, starts, c, qx, qy, max_d2, best, best_slot):
    for s in range(starts[c], starts[c + 1]):
        ex = qx - sx[s]
        ey = qy - sy[s]
        d2 = ex * ex + ey * ey
        if d2 < max_d2 and (
            d2 < best or (d2 == best and best_slot >= 0 and order[s] < order[best_slot])
        ):
            best = d2
            best_slot = s
    return best, best_slot


@numba.njit(cache=True, nogil=True)
def _nearest_within(sx, sy, order, starts, x0, y0, cell, nx, ny, qx, qy, max_d2, reach):
    """(squared distance, slot in the sorted arrays) of the nearest point closer than
    sqrt(max_d2), ties to the lower input index; (inf, -1) when there is none. Rings of cells
    from the query's own outwards, so that a near point found early prunes the outer rings."""
    best = np.inf
    best_slot = -1
    ci = math.floor((qx - x0) / cell)
    cj = math.floor((qy - y0) / cell)
    for ring in range(reach + 1):
        # every cell of this ring is at least (ring - 1) cells from the query
        if ring > 1:
            gap = (ring - 1) * cell
            if gap * gap >= min(best, max_d2):
                break
        for j in range(max(cj - ring, 0), min(cj + ring, ny - 1) + 1):
            edge_row = j == cj - ring or j == cj + ring
            dy = _gap(qy, y0 + j * cell, cell)
            i = ci - ring
            while i <= ci + ring:
                if 0 <= i < nx:
                    dx = _gap(qx, x0 + i * cell, cell)
                    if dx * dx + dy * dy < min(best, max_d2):
                        best, best_slot = _scan_cell(
                            sx, sy, order, starts, j * nx + i, qx, qy, max_d2, best, best_slot
                        )
                # inner rows of the ring: only its two side cells
                i += 1 if (edge_row or ring == 0) else 2 * ring
    return best, best_slot


@numba.njit(cache=True, nogil=True)
def _correspond(
    px, py, sx, sy, order, starts, x0, y0, cell, nx, ny, max_d2, reach, src_of, slot_of
):
    """Nearest target within reach of every moved source point: (count, fitness, inlier RMSE),
    the pairs in src_of / slot_of (as open3d's GetRegistrationResultAndCorrespondences)."""
    n = px.shape[0]
    m = 0
    err2 = 0.0
    for p in range(n):
        d2, s = _nearest_within(
            sx, sy, order, starts, x0, y0, cell, nx, ny, px[p], py[p], max_d2, reach
        )
        if s >= 0:
            src_of[m] = p
            slot_of[m] = s
            err2 += d2
            m += 1
    if m == 0:
        return 0, 0.0, 0.0
    return m, m / n, math.sqrt(err2 / m)


@numba.njit(cache=True, nogil=True)
def icp_point_to_point(
    src,
    sx,
    sy,
    order,
    starts,
    x0,
    y0,
    cell,
    nx,
    ny,
    init,
    max_corr,
    rel_fitness,
    rel_rmse,
    max_iter,
):
    """Planar point-to-point ICP, iteration for iteration open3d's ``registration_icp`` with
    ``TransformationEstimationPointToPoint`` on points with z = 0: nearest target point within
    ``max_corr`` per source point, then Umeyama's closed form (for a planar cross-covariance
    its rotation is the orthogonal polar factor of the 2x2 block, a reflection included, as
    Eigen's 3-D SVD gives it), the update applied to the moved points, until both fitness and
    inlier RMSE change by less than the tolerances. ``init``: 3x3 homogeneous; returns the same."""
    n = src.shape[0]
    T = init.copy()
    px = np.empty(n)
    py = np.empty(n)
    for p in range(n):
        px[p] = T[0, 0] * src[p, 0] + T[0, 1] * src[p, 1] + T[0, 2]
        py[p] = T[1, 0] * src[p, 0] + T[1, 1] * src[p, 1] + T[1, 2]
    src_of = np.empty(n, dtype=np.int64)
    slot_of = np.empty(n, dtype=np.int64)
    max_d2 = max_corr * max_corr
    reach = math.ceil(max_corr / cell)
    m, fitness, rmse = _correspond(
        px, py, sx, sy, order, starts, x0, y0, cell, nx, ny, max_d2, reach, src_of, slot_of
    )
    for _ in range(max_iter):
        c = 1.0
        s = 0.0
        tx = 0.0
        ty = 0.0
        reflect = False
        if m > 0:
            msx = msy = mdx = mdy = 0.0
            for k in range(m):
                msx += px[src_of[k]]
                msy += py[src_of[k]]
                mdx += sx[slot_of[k]]
                mdy += sy[slot_of[k]]
            msx /= m
            msy /= m
            mdx /= m
            mdy /= m
            h00 = h01 = h10 = h11 = 0.0  # sum (d - md)(s - ms)^T
            for k in range(m):
                ax = px[src_of[k]] - msx
                ay = py[src_of[k]] - msy
                bx = sx[slot_of[k]] - mdx
                by = sy[slot_of[k]] - mdy
                h00 += bx * ax
                h01 += bx * ay
                h10 += by * ax
                h11 += by * ay
            if h00 * h11 - h01 * h10 >= 0.0:
                ang = math.atan2(h10 - h01, h00 + h11)
            else:
                ang = math.atan2(h10 + h01, h00 - h11)
                reflect = True
            c = math.cos(ang)
            s = math.sin(ang)
        # update U = [[c, -s], [s, c]] (or [[c, s], [s, -c]]), t = md - U ms
        u00 = c
        u01 = s if reflect else -s
        u10 = s
        u11 = -c if reflect else c
        if m > 0:
            tx = mdx - (u00 * msx + u01 * msy)
            ty = mdy - (u10 * msx + u11 * msy)
        t00 = u00 * T[0, 0] + u01 * T[1, 0]
        t01 = u00 * T[0, 1] + u01 * T[1, 1]
        t02 = u00 * T[0, 2] + u01 * T[1, 2] + tx
        t10 = u10 * T[0, 0] + u11 * T[1, 0]
        t11 = u10 * T[0, 1] + u11 * T[1, 1]
        t12 = u10 * T[0, 2] + u11 * T[1, 2] + ty
        T[0, 0] = t00
        T[0, 1] = t01
        T[0, 2] = t02
        T[1, 0] = t10
        T[1, 1] = t11
        T[1, 2] = t12
        for p in range(n):
            x = px[p]
            y = py[p]
            px[p] = u00 * x + u01 * y + tx
            py[p] = u10 * x + u11 * y + ty
        prev_fitness = fitness
        prev_rmse = rmse
        m, fitness, rmse = _correspond(
            px, py, sx, sy, order, starts, x0, y0, cell, nx, ny, max_d2, reach, src_of, slot_of
        )
        if abs(prev_fitness - fitness) < rel_fitness and abs(prev_rmse - rmse) < rel_rmse:
            break
    return T
