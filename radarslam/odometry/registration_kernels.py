"""The refinement and the covariance's per-point sums, compiled by numba.

Both run a few hundred points through a dozen small numpy operations several times per
frame; numpy's per-call overhead, not the arithmetic, made up most of their time. The
covariance kernel returns the sums that :mod:`.registration` turns into a covariance, so the
maths stays readable there; the refinement runs whole here (:func:`refine_pose`), its steps
written out as ``ScanToMapRegistration._refine`` describes them. Results are the same as numpy's
up to the order of floating-point operations.

Like :mod:`radarslam.grid_kernels`, imported only by its callers, so that loading the package
does not load numba.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from radarslam.grid_kernels import query


@numba.njit(cache=True, nogil=True)
def refine_sums(pb, pw, dist, idx, cloud, max_dist, s2, rot):
    """Geman-McClure-weighted normal equations of point-to-local-mean residuals, over the points
    whose ``k`` nearest map points all lie within ``max_dist``.

    Returns (used points, sw, hxt, hyt, htt, gx, gy, gt): H = [[sw, 0, hxt], [0, sw, hyt],
    [hxt, hyt, htt]], g = [gx, gy, gt] (see ScanToMapRegistration._refine)."""
    m, k = dist.shape
    used = 0
    sw = hxt = hyt = htt = gx = gy = gt = 0.0
    for p in range(m):
        if not dist[p, k - 1] < max_dist:  # sorted: the k-th is the farthest
            continue
        mx = 0.0
        my = 0.0
        for j in range(k):
            mx += cloud[idx[p, j], 0]
            my += cloud[idx[p, j], 1]
        used += 1
        rx = pw[p, 0] - mx / k
        ry = pw[p, 1] - my / k
        rbx = rx * rot[0, 0] + ry * rot[1, 0]  # body frame, R^T r
        rby = rx * rot[0, 1] + ry * rot[1, 1]
        w = s2 / (s2 + rx * rx + ry * ry)
        w = w * w
        qx = -pb[p, 1]
        qy = pb[p, 0]
        sw += w
        hxt += w * qx
        hyt += w * qy
        htt += w * (qx * qx + qy * qy)
        gx += w * rbx
        gy += w * rby
        gt += w * (qx * rbx + qy * rby)
    return used, sw, hxt, hyt, htt, gx, gy, gt


@numba.njit(cache=True, nogil=True)
def covariance_sums(pb, pw, dist, idx, cloud, max_dist, rot):
    """Point-to-line (or point-to-point, for compact neighbourhoods) Hessian at the solution.

    Returns (matched points, H as a (3, 3) array, squared residual sum, residual count)."""
    m, k = dist.shape
    hess = np.zeros((3, 3))
    matched = 0
    sq = 0.0
    n_res = 0
    for p in range(m):
        if not dist[p, 0] < max_dist:
            continue
        matched += 1
        ax = 0.0
        ay = 0.0
        for j in range(k):
            ax += cloud[idx[p, j], 0]
            ay += cloud[idx[p, j], 1]
        ax /= k
        ay /= k
        sxx = syy = sxy = 0.0
        for j in range(k):
            cx = cloud[idx[p, j], 0] - ax
            cy = cloud[idx[p, j], 1] - ay
            sxx += cx * cx
            syy += cy * cy
            sxy += cx * cy
        half_tr = 0.5 * (sxx + syy)
        rad = np.hypot(0.5 * (sxx - syy), sxy)
        small = half_tr - rad
        large = half_tr + rad
        dx = pw[p, 0] - cloud[idx[p, 0], 0]
        dy = pw[p, 1] - cloud[idx[p, 0], 1]
        px = -pb[p, 1]  # perp(p): d/d(theta) of R (p + th perp(p))
        py = pb[p, 0]
        if large > 4.0 * max(small, 1e-12):
            # the normal is perpendicular to the major axis, 0.5 atan2(2 sxy, sxx - syy)
            ang = 0.5 * np.arctan2(2.0 * sxy, sxx - syy)
            nx = -np.sin(ang)
            ny = np.cos(ang)
            lx = nx * rot[0, 0] + ny * rot[1, 0]  # R^T n
            ly = nx * rot[0, 1] + ny * rot[1, 1]
            lth = lx * px + ly * py
            hess[0, 0] += lx * lx
            hess[1, 1] += ly * ly
            hess[0, 1] += lx * ly
            hess[0, 2] += lx * lth
            hess[1, 2] += ly * lth
            hess[2, 2] += lth * lth
            r = nx * dx + ny * dy
            sq += r * r
            n_res += 1
        else:  # rows R [I, perp(p)]: J^T J = [[I, perp], [perp^T, |p|^2]]
            hess[0, 0] += 1.0
            hess[1, 1] += 1.0
            hess[0, 2] += px
            hess[1, 2] += py
            hess[2, 2] += px * px + py * py
            sq += dx * dx + dy * dy
            n_res += 2
    hess[1, 0] = hess[0, 1]
    hess[2, 0] = hess[0, 2]
    hess[2, 1] = hess[1, 2]
    return matched, hess, sq, n_res


@numba.njit(cache=True, nogil=True)
def refine_pose(
    grid_sx, grid_sy, grid_order, grid_starts, x0, y0, cell, nx, ny, n_points,
    cloud, pb, x, y, yaw, k, max_dist, s2, iterations, max_extrapolation, metric,
):  # fmt: skip
    """The whole refinement (ScanToMapRegistration._refine) on planar ``(x, y, yaw)``: per step
    the bounded k-NN query of the map mirror's grid (``grid_*`` .. ``n_points``, as
    :class:`~radarslam.neighbors.GridIndex` holds them), :func:`refine_sums`, the damped 3x3
    Gauss-Newton solve in closed form, Aitken's extrapolation and the SE(2) update. Written as
    numpy around the two kernels, each step paid about 40 us of Python.

    Returns (x, y, yaw, steps taken); no step where fewer than 3 points qualify (or the normal
    equations are singular), so the caller keeps its pose bit for bit."""
    n = pb.shape[0]
    pw = np.empty((n, 2))
    rot = np.empty((2, 2))
    px = py = pt = 0.0  # previous step
    steps = 0
    for _ in range(iterations):
        c = math.cos(yaw)
        s = math.sin(yaw)
        rot[0, 0] = c
        rot[0, 1] = -s
        rot[1, 0] = s
        rot[1, 1] = c
        for p in range(n):
            pw[p, 0] = pb[p, 0] * c - pb[p, 1] * s + x
            pw[p, 1] = pb[p, 0] * s + pb[p, 1] * c + y
        dist, idx = query(
            grid_sx, grid_sy, grid_order, grid_starts, x0, y0, cell, nx, ny,
            pw, k, max_dist, 0.0, n_points,
        )  # fmt: skip
        used, sw, hxt, hyt, htt, gx, gy, gt = refine_sums(
            pb, pw, dist, idx, cloud, max_dist, s2, rot
        )
        if used < 3:
            break
        # J = R [I, perp(p)]: J^T J = [[I, perp], [perp^T, |p|^2]], J^T r = [rb, perp . rb], so
        # H = [[sw, 0, hxt], [0, sw, hyt], [hxt, hyt, htt]] + 1e-9 I; delta = -H^-1 g (cofactors)
        a = sw + 1e-9
        e = htt + 1e-9
        c00 = a * e - hyt * hyt
        c01 = hxt * hyt
        c02 = -a * hxt
        c11 = a * e - hxt * hxt
        c12 = -a * hyt
        c22 = a * a
        det = a * c00 + hxt * c02
        if det == 0.0 or not math.isfinite(det):
            break
        dx = -(c00 * gx + c01 * gy + c02 * gt) / det
        dy = -(c01 * gx + c11 * gy + c12 * gt) / det
        dt = -(c02 * gx + c12 * gy + c22 * gt) / det
        scale = 1.0
        if steps > 0 and max_extrapolation > 1.0:
            # Yaw weighted as the arc at 10 m (metric), so that both parts count alike.
            wx, wy, wt = px * metric[0], py * metric[1], pt * metric[2]
            denom = wx * px + wy * py + wt * pt
            rho = (wx * dx + wy * dy + wt * dt) / denom if denom > 0 else 0.0
            if 0.0 < rho < 1.0:
                scale = min(1.0 / (1.0 - rho), max_extrapolation)
        rx, ry, th = scale * dx, scale * dy, scale * dt
        # pose @ exp_se2((rx, ry, th)), projected back on SE(2) as lie.planar does
        if abs(th) < 1e-6:
            va, vb = 1.0 - th * th / 6.0, 0.5 * th
        else:
            va, vb = math.sin(th) / th, (1.0 - math.cos(th)) / th
        tx = va * rx - vb * ry
        ty = vb * rx + va * ry
        x += c * tx - s * ty
        y += s * tx + c * ty
        ct, st = math.cos(th), math.sin(th)
        yaw = math.atan2(s * ct + c * st, c * ct - s * st)
        px, py, pt = dx, dy, dt
        steps += 1
        if max(abs(dx), abs(dy), abs(dt)) < 1e-4:  # 0.1 mm, 0.006 deg
            break
    return x, y, yaw, steps
