"""The refinement's and the covariance's per-point sums, compiled by numba.

Both run a few hundred points through a dozen small numpy operations four times per frame;
numpy's per-call overhead, not the arithmetic, made up most of their time. Each kernel returns
the sums that :mod:`.registration` turns into a Gauss-Newton step or a covariance, so the maths
stays readable there; the sums are the same up to the order of floating-point additions.

Like :mod:`radarslam.grid_kernels`, imported only by its callers, so that loading the package
does not load numba.
"""

from __future__ import annotations

import numba
import numpy as np


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
