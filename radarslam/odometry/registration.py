"""Scan-to-map registration against kiss-icp's voxel-hash local map.

We call kiss-icp's building blocks directly (``VoxelHashMap``, ``voxel_down_sample``,
``Registration.align_points_to_map``) instead of its ``KissICP`` pipeline, so that the initial
guess is the Doppler-predicted pose rather than kiss-icp's constant-velocity extrapolation, and
so that frames with too few points skip registration instead of feeding the extrapolation
(which, after many empty frames, de-orthogonalises the rotation until Sophus aborts the
process). Every pose handed to kiss-icp is an exact SE(2)
pose built here, and its output is projected back onto SE(2).

kiss-icp's few point-to-point iterations are followed by a Gauss-Newton refinement on
point-to-local-mean residuals (``refine_iterations``; why in
:meth:`ScanToMapRegistration._refine`). With ``point_to_point="fallback"`` the refinement starts
from the seed itself and kiss-icp runs only where the refinement cannot start (a young or
sparse map).

kiss-icp reports no uncertainty, so the covariance of an alignment is computed here from the
point-to-line Hessian at the solution (Censi-style ``sigma^2 H^-1``): each source point's nearest
map points give a local line (PCA), the residual is the distance along its normal. A row of
reflectors along one wall therefore leaves the motion along the wall unconstrained, which the
fusion then takes from the Doppler prediction. The map mirror used for the refinement and these
correspondences is an exact nearest-neighbour grid of kiss-icp's map (~20k points,
:class:`~radarslam.neighbors.GridIndex`) rebuilt every ``mirror_every`` map updates.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from radarslam.geometry import se2_to_matrix
from radarslam.odometry.lie import exp_se2, planar
from radarslam.odometry.linalg3 import inv3

if TYPE_CHECKING:
    from radarslam.neighbors import GridIndex

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
    from radarslam.odometry.registration_kernels import covariance_sums, refine_pose

    for module in ("kiss_icp.mapping", "kiss_icp.registration", "kiss_icp.voxelization"):
        importlib.import_module(module)
    cloud = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    pts = cloud[:2] + 0.1
    grid = GridIndex(cloud)
    dist, idx = grid.query(pts, 3, 2.0, nearest_within=2.0)
    refine_pose(
        *grid.kernel_arguments, grid.n, cloud, pts, 0.0, 0.0, 0.0, 3, 2.0, 1.0, 1, 8.0, _STEP_METRIC
    )
    covariance_sums(pts, pts, dist, idx, cloud, 2.0, np.eye(2))


class ScanToMapRegistration:
    """Registration of ego-frame points (z = 0) to a world-frame kiss-icp voxel-hash map."""

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
        point_to_point: str = "always",
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
        if point_to_point not in ("always", "fallback"):
            raise ValueError(
                f"point_to_point must be 'always' or 'fallback', got {point_to_point!r}"
            )
        self.point_to_point = point_to_point
        self.map = VoxelHashMap(voxel_size_m, max_range_m, max_points_per_voxel)
        # One thread: deterministic, and the machines this runs on are shared.
        self.registration = Registration(max_num_iterations, convergence_criterion, 1)
        self._mirror: tuple[GridIndex, np.ndarray] | None = None
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
        pose = planar(initial_guess)
        refined = False
        if self.point_to_point == "fallback" and self.refine_iterations:
            pose, refined = self._refine(source, pose, 3.0 * sigma, sigma)
        if not refined:
            pose = self.registration.align_points_to_map(
                points=source,
                voxel_map=self.map,
                initial_guess=pose,
                max_correspondance_distance=3.0 * sigma,
                kernel=sigma,
            )
            pose = planar(np.asarray(pose, dtype=np.float64))
            if self.refine_iterations:
                pose, _ = self._refine(source, pose, 3.0 * sigma, sigma)
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

    def _refine(
        self, source: np.ndarray, pose: np.ndarray, max_dist: float, sigma: float
    ) -> tuple[np.ndarray, bool]:
        """Gauss-Newton on point-to-local-mean residuals from ``pose`` (the seed, or kiss-icp's
        solution): (refined pose, whether a step was taken).

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
        pull the scan back along the track. With fewer than 3 such points no step is taken
        (a young or sparse map; ``point_to_point="fallback"`` then runs kiss-icp).
        """
        mirror = self._mirror_tree()
        k = self.line_neighbors
        if mirror is None or len(mirror[1]) < k or len(source) < 3 or not self.refine_iterations:
            return pose, False
        tree, cloud = mirror
        from radarslam.odometry.registration_kernels import refine_pose

        # The steps run compiled (registration_kernels.refine_pose): per step the bounded k-NN
        # query, the weighted sums, the 3x3 solve with a 1e-9 damping, the extrapolation and the
        # SE(2) update; it stops once a step is below 0.1 mm and 0.006 deg.
        x, y, yaw, steps = refine_pose(
            *tree.kernel_arguments,
            tree.n,
            cloud,
            np.ascontiguousarray(source[:, :2], dtype=np.float64),
            float(pose[0, 3]),
            float(pose[1, 3]),
            math.atan2(pose[1, 0], pose[0, 0]),
            k,
            float(max_dist),
            float(sigma) ** 2,
            self.refine_iterations,
            float(self.refine_max_extrapolation),
            _STEP_METRIC,
        )
        if not steps:
            return pose, False
        return se2_to_matrix(x, y, yaw), True

    # --- covariance ---------------------------------------------------------------------------

    def _mirror_tree(self) -> tuple[GridIndex, np.ndarray] | None:
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
