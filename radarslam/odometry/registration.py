"""Scan-to-map registration with kiss-icp's own C++ registration and voxel-hash local map.

We call kiss-icp's building blocks directly (``Registration.align_points_to_map``,
``VoxelHashMap``, ``AdaptiveThreshold``, ``voxel_down_sample``) instead of its ``KissICP`` pipeline,
so that the initial guess is the Doppler-predicted pose rather than kiss-icp's constant-velocity
extrapolation, and so that frames with too few points skip registration instead of feeding the
extrapolation (which, after many empty frames, de-orthogonalises the rotation until Sophus
aborts the process). Every pose handed to kiss-icp is an exact SE(2)
pose built here, and its output is projected back onto SE(2).

kiss-icp's few iterations are followed by a Gauss-Newton refinement on point-to-local-mean
residuals (``refine_iterations``; why in :meth:`ScanToMapRegistration._refine`).

kiss-icp reports no uncertainty, so the covariance of an alignment is computed here from the
point-to-line Hessian at the solution (Censi-style ``sigma^2 H^-1``): each source point's nearest
map points give a local line (PCA), the residual is the distance along its normal. A row of
reflectors along one wall therefore leaves the motion along the wall unconstrained, which the
fusion then takes from the Doppler prediction. The map mirror used for the refinement and these
correspondences is an exact nearest-neighbour grid of kiss-icp's map (~20k points,
:class:`~radarslam.neighbors.GridIndex`) rebuilt every ``mirror_every`` map updates.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from radarslam.odometry.lie import exp_se2, planar
from radarslam.odometry.linalg3 import inv3, solve3

#: Metric on refinement steps (x, y, yaw): yaw as the arc it sweeps at 10 m.
_STEP_METRIC = np.array([1.0, 1.0, 100.0])


@dataclass(frozen=True)
class RegistrationResult:
    world_from_ego: np.ndarray  # 4x4, SE(2)
    covariance: np.ndarray  # (3, 3) body-frame tangent (x, y, yaw) of the aligned pose
    num_source: int  # source points after voxelisation
    num_matched: int  # source points with a map line within the correspondence distance
    residual_rms_m: float
    sigma_m: float  # kiss-icp's kernel / threshold used


def load_kernels() -> None:
    """Load the compiled code the registration runs: kiss-icp's modules, and the map mirror's
    grid and the refinement's and covariance's sums, run once on a tiny map. numba loads those
    kernels, and itself, on first use: about 1 s of CPU per process (a compile, several seconds,
    on the first run after an install). Called before a stream's first frame, it keeps that
    frame from arriving a second late; the odometry benchmark calls it before its workers fork
    and reports it as start-up."""
    import importlib

    from radarslam.neighbors import GridIndex
    from radarslam.odometry.registration_kernels import covariance_sums, refine_sums

    for module in ("kiss_icp.mapping", "kiss_icp.registration", "kiss_icp.voxelization"):
        importlib.import_module(module)
    cloud = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    pts = cloud[:2] + 0.1
    dist, idx = GridIndex(cloud).query(pts, 3, 2.0, nearest_within=2.0)
    rot = np.eye(2)
    refine_sums(pts, pts, dist, idx, cloud, 2.0, 1.0, rot)
    covariance_sums(pts, pts, dist, idx, cloud, 2.0, rot)


class ScanToMapRegistration:
    """kiss-icp registration of ego-frame points (z = 0) to a world-frame voxel-hash map."""

    def __init__(
        self,
        *,
        voxel_size_m: float,
        max_range_m: float,
        max_points_per_voxel: int,
        max_num_iterations: int,
        convergence_criterion: float,
        fixed_sigma_m: float,
        point_sigma_m: float,
        line_neighbors: int,
        mirror_every: int,
        refine_iterations: int = 0,
        refine_max_extrapolation: float = 1.0,
    ):
        from kiss_icp.mapping import VoxelHashMap
        from kiss_icp.registration import Registration

        self.voxel_size_m = voxel_size_m
        self.max_range_m = max_range_m
        self.sigma_m = fixed_sigma_m
        self.point_sigma_m = point_sigma_m
        self.line_neighbors = line_neighbors
        self.mirror_every = mirror_every
        self.refine_iterations = refine_iterations
        self.refine_max_extrapolation = refine_max_extrapolation
        self.map = VoxelHashMap(voxel_size_m, max_range_m, max_points_per_voxel)
        # One thread: deterministic, and the machines this runs on are shared.
        self.registration = Registration(max_num_iterations, convergence_criterion, 1)
        self._mirror = None
        self._mirror_age = 0

    @property
    def empty(self) -> bool:
        return self.map.empty()

    def voxelize(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(source for registration, points to add to the map), as kiss-icp does."""
        from kiss_icp.voxelization import voxel_down_sample

        frame = voxel_down_sample(points, self.voxel_size_m * 0.5)
        source = voxel_down_sample(frame, self.voxel_size_m * 1.5)
        return source, frame

    def sigma(self) -> float:
        return float(self.sigma_m)

    def align(self, source: np.ndarray, initial_guess: np.ndarray) -> RegistrationResult:
        sigma = self.sigma()
        guess = planar(initial_guess)
        pose = self.registration.align_points_to_map(
            points=source,
            voxel_map=self.map,
            initial_guess=guess,
            max_correspondance_distance=3.0 * sigma,
            kernel=sigma,
        )
        pose = planar(np.asarray(pose, dtype=np.float64))
        if self.refine_iterations:
            pose = self._refine(source, pose, 3.0 * sigma, sigma)
        cov, matched, rms = self._covariance(source, pose, 3.0 * sigma)
        return RegistrationResult(pose, cov, len(source), matched, rms, sigma)

    def align_over_yaw(
        self, source: np.ndarray, initial_guess: np.ndarray, half_width_rad: float, step_rad: float
    ) -> RegistrationResult:
        """:meth:`align` from seeds turned by yaw offsets over ``+-half_width_rad``, ``step_rad``
        apart. The alignment from ``initial_guess`` itself stands unless another matches more
        than 2 source points more; then, of those within 2 of the most, the one with the lowest
        residual (a scan turned off its place matches fewer points, and those more loosely).
        Against a map of a frame or two every turn matches about as well, and the guess wins."""
        n = int(np.ceil(half_width_rad / step_rad))
        results = [
            self.align(source, planar(initial_guess @ exp_se2(np.array([0.0, 0.0, k * step_rad]))))
            for k in range(-n, n + 1)
        ]
        most = max(r.num_matched for r in results)
        if results[n].num_matched >= most - 2:
            return results[n]
        near = [r for r in results if r.num_matched >= most - 2 and np.isfinite(r.residual_rms_m)]
        return min(near, key=lambda r: r.residual_rms_m) if near else results[n]

    def update(self, frame_points: np.ndarray, world_from_ego: np.ndarray) -> None:
        """Add ego-frame points at the pose."""
        if len(frame_points):
            self.map.update(frame_points, planar(world_from_ego))
            self._mirror_age += 1

    # --- refinement ---------------------------------------------------------------------------

    def _refine(self, source: np.ndarray, pose: np.ndarray, max_dist: float, sigma: float):
        """Gauss-Newton on point-to-local-mean residuals, from kiss-icp's solution.

        kiss-icp matches each point to the single nearest map point. Radar maps are clouds of
        noisy returns around each reflector (up to 20 per voxel), so a slightly rotated scan still
        finds a near neighbour inside every cloud and the point-to-point cost is almost flat in
        yaw: the registration stays where the Doppler prediction put it. The mean of a point's
        ``line_neighbors`` nearest map points (within the correspondence distance) averages that
        noise out and restores the pull towards the reflector. Weights: Geman-McClure with
        kiss-icp's kernel ``sigma``.

        The nearest neighbours of a point lie on its side of the cloud, so the mean follows the
        point as it moves (a mean shift): each step covers only part of the way, and consecutive
        steps point the same way with a ratio ``rho``. Aitken's extrapolation scales a step by
        ``1 / (1 - rho)``, the sum of that geometric tail, capped at
        ``refine_max_extrapolation``; a step that turns back (``rho <= 0``) is taken as is.

        Only points with all ``line_neighbors`` map points inside the correspondence distance
        take part: at the edge of the map (far ahead, a newly
        seen object) the neighbours lie on the side the vehicle came from, and their mean would
        pull the scan back along the track.
        """
        mirror = self._mirror_tree()
        k = self.line_neighbors
        if mirror is None or len(mirror[1]) < k or len(source) < 3:
            return pose
        tree, cloud = mirror
        from radarslam.odometry.registration_kernels import refine_sums

        pb = np.ascontiguousarray(source[:, :2])
        s2 = sigma**2
        previous = None
        for _ in range(self.refine_iterations):
            rot, t = pose[:2, :2], pose[:2, 3]
            pw = pb @ rot.T + t
            # Bounded query: much cheaper than plain k-NN where the map is sparse.
            dist, idx = tree.query(pw, k, max_dist)
            used, sw, hxt, hyt, htt, gx, gy, gt = refine_sums(
                pb, pw, dist, idx, cloud, max_dist, s2, np.ascontiguousarray(rot)
            )
            if used < 3:
                return pose
            # J = R [I, perp(p)]: J^T J = [[I, perp], [perp^T, |p|^2]], J^T r = [rb, perp . rb].
            hess = np.array([[sw, 0.0, hxt], [0.0, sw, hyt], [hxt, hyt, htt]])
            grad = np.array([gx, gy, gt])
            delta = -solve3(hess + np.eye(3) * 1e-9, grad)
            scale = 1.0
            if previous is not None and self.refine_max_extrapolation > 1.0:
                # Yaw weighted as the arc at 10 m, so that both parts count alike.
                wp = previous * _STEP_METRIC
                denom = float(wp @ previous)
                rho = float(wp @ delta) / denom if denom > 0 else 0.0
                if 0.0 < rho < 1.0:
                    scale = min(1.0 / (1.0 - rho), self.refine_max_extrapolation)
            pose = planar(pose @ exp_se2(scale * delta))
            previous = delta
            if np.abs(delta).max() < 1e-4:  # 0.1 mm, 0.006 deg
                break
        return pose

    # --- covariance ---------------------------------------------------------------------------

    def _mirror_tree(self):
        if self._mirror is None or self._mirror_age >= self.mirror_every:
            from radarslam.neighbors import GridIndex

            cloud = np.ascontiguousarray(self.map.point_cloud()[:, :2])
            # The same neighbours as scipy's cKDTree, at a tenth of its build time and a fifth of
            # its query time on these maps (GridIndex's doc).
            self._mirror = None
            if len(cloud):
                self._mirror = (GridIndex(cloud, cell_m=self.voxel_size_m), cloud)
            self._mirror_age = 0
        return self._mirror

    def _covariance(
        self, source: np.ndarray, pose: np.ndarray, max_dist: float
    ) -> tuple[np.ndarray, int, float]:
        huge = np.eye(3) * 1e6
        mirror = self._mirror_tree()
        k = self.line_neighbors
        if mirror is None or len(mirror[1]) < k or len(source) < 3:
            return huge, 0, float("nan")
        tree, cloud = mirror
        from radarslam.odometry.registration_kernels import covariance_sums

        rot, t = pose[:2, :2], pose[:2, 3]
        p_body = np.ascontiguousarray(source[:, :2])
        p_world = p_body @ rot.T + t
        # Only points with a neighbour within max_dist count, so the search may give up on others.
        dist, idx = tree.query(p_world, k, nearest_within=max_dist)
        # Per point: the local line of its k nearest map points (PCA of their scatter in closed
        # form) and the point-to-line row n^T R [I, perp(p)], or point-to-point rows where the
        # neighbours form a compact blob, which constrains both directions.
        m, hess, sq, n_res = covariance_sums(
            p_body, p_world, dist, idx, cloud, max_dist, np.ascontiguousarray(rot)
        )
        if m < 3:
            return huge, m, float("nan")
        mse = sq / n_res
        # Residual variance, floored at the sensor's point noise: correlated correspondences would
        # otherwise make a handful of lucky matches look arbitrarily precise.
        var = max(mse, self.point_sigma_m**2)
        cov = inv3(hess / var + np.eye(3) * 1e-6)
        return 0.5 * (cov + cov.T), m, float(np.sqrt(mse))
