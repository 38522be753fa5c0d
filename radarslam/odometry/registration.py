"""Scan-to-map registration with kiss-icp's own C++ registration and voxel-hash local map.

We call kiss-icp's building blocks directly (``Registration.align_points_to_map``,
``VoxelHashMap``, ``AdaptiveThreshold``, ``voxel_down_sample``) instead of its ``KissICP`` pipeline,
so that the initial guess is the Doppler-predicted pose rather than kiss-icp's constant-velocity
extrapolation, and so that frames with too few points skip registration instead of feeding the
extrapolation (which, after many empty frames, de-orthogonalises the rotation until Sophus
aborts the process: dependencies.md pitfall 4). Every pose handed to kiss-icp is an exact SE(2)
pose built here, and its output is projected back onto SE(2).

kiss-icp reports no uncertainty, so the covariance of an alignment is computed here from the
point-to-line Hessian at the solution (Censi-style ``sigma^2 H^-1``): each source point's nearest
map points give a local line (PCA), the residual is the distance along its normal. A row of
reflectors along one wall therefore leaves the motion along the wall unconstrained, which the
fusion then takes from the Doppler prediction. The map mirror used for these correspondences is
a KD-tree of kiss-icp's map rebuilt every ``mirror_every`` frames (cheap: a few thousand points).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from radarslam.odometry.lie import planar


@dataclass(frozen=True)
class RegistrationResult:
    world_from_ego: np.ndarray  # 4x4, SE(2)
    covariance: np.ndarray  # (3, 3) body-frame tangent (x, y, yaw) of the aligned pose
    num_source: int  # source points after voxelisation
    num_matched: int  # source points with a map line within the correspondence distance
    residual_rms_m: float
    sigma_m: float  # kiss-icp's kernel / threshold used


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
        threshold: str,
        fixed_sigma_m: float,
        min_sigma_m: float,
        initial_sigma_m: float,
        min_motion_m: float,
        point_sigma_m: float,
        line_neighbors: int,
        mirror_every: int,
    ):
        from kiss_icp.mapping import VoxelHashMap
        from kiss_icp.registration import Registration
        from kiss_icp.threshold import AdaptiveThreshold, FixedThreshold

        self.voxel_size_m = voxel_size_m
        self.max_range_m = max_range_m
        self.min_sigma_m = min_sigma_m
        self.point_sigma_m = point_sigma_m
        self.line_neighbors = line_neighbors
        self.mirror_every = mirror_every
        self.map = VoxelHashMap(voxel_size_m, max_range_m, max_points_per_voxel)
        # One thread: deterministic, and the machines this runs on are shared.
        self.registration = Registration(max_num_iterations, convergence_criterion, 1)
        if threshold == "fixed":
            self.threshold = FixedThreshold(fixed_sigma_m)
        else:

            class _Cfg:  # the minimal shape AdaptiveThreshold reads from a KISSConfig
                class adaptive_threshold:
                    initial_threshold = initial_sigma_m
                    min_motion_th = min_motion_m

                class data:
                    max_range = max_range_m

            self.threshold = AdaptiveThreshold(_Cfg)
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
        return max(float(self.threshold.get_threshold()), self.min_sigma_m)

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
        cov, matched, rms = self._covariance(source, pose, 3.0 * sigma)
        return RegistrationResult(pose, cov, len(source), matched, rms, sigma)

    def update(self, frame_points: np.ndarray, world_from_ego: np.ndarray, deviation=None) -> None:
        """Add ego-frame points at the pose; feed kiss-icp's threshold the model deviation."""
        if deviation is not None:
            self.threshold.update_model_deviation(deviation)
        if len(frame_points):
            self.map.update(frame_points, planar(world_from_ego))
            self._mirror_age += 1

    # --- covariance ---------------------------------------------------------------------------

    def _mirror_tree(self):
        if self._mirror is None or self._mirror_age >= self.mirror_every:
            from scipy.spatial import cKDTree

            cloud = self.map.point_cloud()
            self._mirror = (cKDTree(cloud[:, :2]), cloud[:, :2]) if len(cloud) else None
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
        rot, t = pose[:2, :2], pose[:2, 3]
        p_body = source[:, :2]
        p_world = p_body @ rot.T + t
        dist, idx = tree.query(p_world, k=k)
        ok = dist[:, 0] < max_dist
        if ok.sum() < 3:
            return huge, int(ok.sum()), float("nan")
        nb = cloud[idx[ok]]  # (m, k, 2)
        centred = nb - nb.mean(axis=1, keepdims=True)
        scatter = np.einsum("mki,mkj->mij", centred, centred)
        _, vecs = np.linalg.eigh(scatter)
        normal = vecs[:, :, 0]  # smallest-spread direction (world frame)
        spread = np.linalg.eigvalsh(scatter)
        # A compact blob (no line) constrains both directions: point-to-point for those.
        linear = spread[:, 1] > 4.0 * np.maximum(spread[:, 0], 1e-12)
        pw, pb = p_world[ok], p_body[ok]
        r_line = np.einsum("mi,mi->m", normal, pw - nb[:, 0])
        rows, res = [], []
        # d(R (p + rho + th * perp(p)) + t) = R [I, perp(p)] eps
        perp = np.column_stack([-pb[:, 1], pb[:, 0]])
        jac_pt = np.stack(
            [rot[:, 0][None, :].repeat(len(pb), 0), rot[:, 1][None, :].repeat(len(pb), 0)],
            axis=2,
        )  # (m, 2, 2) = R
        jac_th = perp @ rot.T  # (m, 2) = R perp(p)
        full = np.concatenate([jac_pt, jac_th[:, :, None]], axis=2)  # (m, 2, 3)
        j_line = np.einsum("mi,mij->mj", normal, full)  # (m, 3)
        rows.append(j_line[linear])
        res.append(r_line[linear])
        pt = ~linear
        if pt.any():
            rows.append(full[pt].reshape(-1, 3))
            res.append((pw[pt] - nb[pt, 0]).reshape(-1))
        jac = np.concatenate(rows)
        r = np.concatenate(res)
        # Residual variance, floored at the sensor's point noise: correlated correspondences would
        # otherwise make a handful of lucky matches look arbitrarily precise.
        var = max(float(np.mean(r**2)) if len(r) else 0.0, self.point_sigma_m**2)
        hess = jac.T @ jac / var
        cov = np.linalg.inv(hess + np.eye(3) * 1e-6)
        return 0.5 * (cov + cov.T), int(ok.sum()), float(np.sqrt(np.mean(r**2)))
