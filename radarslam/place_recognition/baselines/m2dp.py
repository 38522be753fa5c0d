"""M2DP (He, Wang, Zhang, IROS 2016): a 192-D global descriptor from 2-D projections, in numpy.

1. Centre the cloud on its centroid and rotate it onto its principal axes (PCA), which removes the
   heading.
2. For p azimuths theta in [0, pi) and q elevations phi in [0, pi/2), project the points on the
   plane with normal m = (cos theta cos phi, sin theta cos phi, sin phi). In each plane, a polar
   grid with l rings of radii r, 4r, ..., l^2 r (r = max distance / l^2) and t sectors counts the
   points; the plane's x axis is the projection of the cloud's first principal axis (or of the
   second when that projection vanishes).
3. The (pq) x (lt) signature matrix A is decomposed by SVD; the descriptor is [u_1; v_1]
   (64 + 128 = 192 values for the defaults). The SVD sign is fixed so that v_1 sums positive.
Radar points are planar (z = 0), as the reference's pseudo-z = 1 after centring.
"""

from __future__ import annotations

import numpy as np

from radarslam.errors import DataError
from radarslam.place_recognition.config import M2DPConfig


def descriptor_dim(cfg: M2DPConfig) -> int:
    return cfg.num_azimuths * cfg.num_elevations + cfg.num_rings * cfg.num_sectors


def m2dp(points: np.ndarray, cfg: M2DPConfig | None = None) -> np.ndarray:
    """(pq + lt,) float32 descriptor of an (N, 2) or (N, 3) cloud; zeros when N < 3."""
    cfg = cfg or M2DPConfig()
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] not in (2, 3):
        raise DataError(f"M2DP: points must be (N, 2) or (N, 3), got shape {pts.shape}")
    if pts.size and not np.all(np.isfinite(pts)):
        raise DataError("M2DP: point coordinates contain NaN or infinity")
    if pts.shape[1] == 2:
        pts = np.column_stack([pts, np.zeros(len(pts))])
    if len(pts) < 3:
        return np.zeros(descriptor_dim(cfg), np.float32)
    pts = pts - pts.mean(axis=0)
    _, vecs = np.linalg.eigh(pts.T @ pts)
    axes = vecs[:, ::-1]  # principal axes, largest variance first
    # eigenvector signs are arbitrary: orient each axis towards the heavier third moment
    skew = np.sum((pts @ axes) ** 3, axis=0)
    axes = axes * np.where(skew < 0, -1.0, 1.0)[None, :]
    if np.linalg.det(axes) < 0:
        axes[:, 2] *= -1
    pts = pts @ axes
    max_r = float(np.max(np.linalg.norm(pts, axis=1)))
    if max_r <= 0:
        return np.zeros(descriptor_dim(cfg), np.float32)
    l_, t_ = cfg.num_rings, cfg.num_sectors
    radii = (np.arange(1, l_ + 1) ** 2) * (max_r / l_**2)
    thetas = np.pi * np.arange(cfg.num_azimuths) / cfg.num_azimuths
    phis = 0.5 * np.pi * np.arange(cfg.num_elevations) / cfg.num_elevations
    rows = []
    ex, ey = np.array([1.0, 0.0, 0.0]), np.array([0.0, 1.0, 0.0])
    for th in thetas:
        for ph in phis:
            m = np.array([np.cos(th) * np.cos(ph), np.sin(th) * np.cos(ph), np.sin(ph)])
            x_axis = ex - (ex @ m) * m
            if np.linalg.norm(x_axis) < 1e-6:
                x_axis = ey - (ey @ m) * m
            x_axis /= np.linalg.norm(x_axis)
            y_axis = np.cross(m, x_axis)
            u, v = pts @ x_axis, pts @ y_axis
            rad = np.hypot(u, v)
            ring = np.minimum(np.searchsorted(radii, rad, side="left"), l_ - 1)
            ang = np.mod(np.arctan2(v, u), 2 * np.pi)
            sector = np.minimum((ang / (2 * np.pi) * t_).astype(np.int64), t_ - 1)
            rows.append(np.bincount(ring * t_ + sector, minlength=l_ * t_))
    a = np.asarray(rows, dtype=np.float64) / len(pts)
    u_mat, _, vt = np.linalg.svd(a, full_matrices=False)
    u1, v1 = u_mat[:, 0], vt[0]
    if v1.sum() < 0:
        u1, v1 = -u1, -v1
    return np.concatenate([u1, v1]).astype(np.float32)
