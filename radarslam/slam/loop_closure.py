"""Geometric verification of place-recognition candidates by registering accumulated local maps.

Radar local maps are sparse and places are often revisited in the opposite direction, so one ICP
from one initial guess is not enough. :class:`LoopVerifier` therefore

1. optionally drops points without ``min_neighbors`` others nearby (single clutter returns),
   then voxel-downsamples both (N, 2) maps;
2. tries heading hypotheses every ``heading_step_deg`` around the initial guess (the default 30
   includes 0, +-90 and 180 deg), all round or within ``heading_range_deg`` of the guess's
   heading; for each, a coarse 2-D correlative search over translation
   (FFT cross-correlation of the rotated query's occupancy with the candidate's blurred occupancy,
   within ``search_radius_m``) places the query;
3. refines the ``refine_top_k`` best hypotheses by ICP (coarse then fine correspondence distance;
   ``backend``: ``grid``, open3d's point-to-point iterations on the compiled neighbour grid of
   :mod:`radarslam.neighbors`, the same poses at a third of open3d's CPU time; or ``open3d``
   itself) and keeps the one with the highest fitness;
4. accepts when fitness, inlier RMSE and grid overlap all pass their thresholds, and derives the
   loop's information matrix from the point-to-point Hessian of the final correspondences.

Poses: the result is ``candidate_from_query`` (4x4, planar). For the pose graph that is
``add_loop(candidate_key, query_key, candidate_from_query, information)``. The information matrix
is in Pose2 tangent order (x, y, theta) for gtsam's right-perturbation convention.
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict
from collections.abc import Hashable
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from pydantic import Field

from radarslam.config import StrictModel
from radarslam.errors import DataError
from radarslam.geometry import se2_to_matrix
from radarslam.io.loops import LoopCandidate, LoopVerification, NodeKey

__all__ = [
    "LoopCandidate",
    "LoopVerification",
    "LoopVerifier",
    "LoopVerifierConfig",
    "NodeKey",
]


class LoopVerifierConfig(StrictModel):
    # Defaults tuned on synthetic cities (street grids alias). Inlier RMSE separates best:
    # correct registrations 0.54-0.59 m, wrong ones mostly >= 0.62 m; fitness and overlap barely
    # separate across days (parked cars change). On 1,365 city candidates these thresholds accept
    # 596/777 correct and 42/588 wrong registrations; the SLAM pipeline rejects the wrong ones
    # that remain by consistency (two agreeing loops to link a session, the map's prediction
    # once linked). 1 m voxels and 30 deg headings are ~3x faster than 0.5 m / 15 deg.
    backend: Literal["grid", "open3d"] = "grid"
    voxel_size_m: float = Field(1.0, gt=0, le=1000)
    min_points: int = Field(30, ge=3)
    heading_step_deg: float = Field(30.0, gt=0, le=360)
    # Heading hypotheses span this window centred on the initial guess's heading (360: all
    # round). A search that knows the relative heading roughly (a turned-image candidate: about
    # 180 deg) tries fewer hypotheses: cheaper, and fewer chances to align a look-alike.
    heading_range_deg: float = Field(360.0, gt=0, le=360)
    correlative_search: bool = True
    search_radius_m: float = Field(15.0, ge=0, le=1000)
    grid_cell_m: float = Field(2.0, gt=0, le=1000)
    refine_top_k: int = Field(2, ge=1)
    coarse_max_correspondence_m: float = Field(3.0, gt=0, le=1000)
    max_correspondence_m: float = Field(1.0, gt=0, le=1000)
    max_iterations: int = Field(30, ge=1)
    # ICP stops when fitness and inlier RMSE change by less than this (relative) between
    # iterations; the acceptance tests are then computed on all points anyway.
    icp_relative_tolerance: float = Field(1e-4, gt=0)
    # The coarse ICP stage aligns an evenly strided subset of at most this many query points (a
    # 1 m voxel local map holds 4-5 k); the fine stage uses them all.
    max_icp_points: int = Field(1500, ge=50)
    # Points farther than this from the key frame are dropped before everything else (None:
    # keep all). Far radar points are what tells look-alike streets apart in the global search,
    # so only the proximity search (a guess from the map) uses this.
    max_range_m: float | None = Field(None, gt=0)
    # Persistence: a point with fewer than this many others within persistence_radius_m of it
    # in its local map is dropped (0: keep all). Clutter that looks static to the Doppler test
    # lies at random around each sweep's sensor, so it piles up along the driven path; two
    # local maps of a street driven in opposite lanes then attract each other's paths.
    min_neighbors: int = Field(0, ge=0)
    persistence_radius_m: float = Field(0.5, gt=0, le=1000)
    # acceptance
    min_fitness: float = Field(0.45, ge=0, le=1)
    max_inlier_rmse_m: float = Field(0.6, gt=0)
    min_overlap: float = Field(0.4, ge=0, le=1)
    # Fraction of query points within tight_correspondence_m of the candidate after alignment:
    # the most discriminative single test across days on the synthetic city (docs/results.md,
    # SLAM settings: of the AutoPlace and turned-image registrations that pass the tests above,
    # the right ones mostly reach 0.15-0.56, the wrong ones (look-alike stretches, streets
    # crossing at 90 deg) 0.07-0.14), because a 1 m voxel map is dense enough that almost any
    # alignment finds neighbours within 1 m, not within 0.3 m.
    tight_correspondence_m: float = Field(0.3, gt=0, le=1000)
    min_tight_fitness: float = Field(0.15, ge=0, le=1)
    overlap_cell_m: float = Field(2.0, gt=0, le=1000)
    # Degeneracy: the smaller / larger eigenvalue of sum(n n^T) over the point-to-line normals of
    # the final correspondences (a PCA of the ``normal_neighbors`` nearest candidate points). A
    # straight street constrains only its cross direction, so a look-alike stretch of it aligns
    # with good fitness metres away along it; 1 means the normals spread evenly. 0 disables.
    min_constraint_ratio: float = Field(0.0, ge=0, le=1)
    normal_neighbors: int = Field(5, ge=2)
    # information = inv(inv(H / sigma^2) + floor): registration Hessian with sigma = inlier RMSE,
    # plus a floor covariance for what point-to-point ICP cannot see (correlated radar points,
    # map blur); the floor bounds how confident a loop closure can ever be.
    min_sigma_m: float = Field(0.1, gt=0)
    floor_sigma_xy_m: float = Field(0.1, ge=0)
    floor_sigma_yaw_deg: float = Field(0.5, ge=0)


def _as_xy(points, what: str) -> np.ndarray:
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] not in (2, 3):
        raise DataError(f"loop verification: {what} must be (N, 2) points, got {arr.shape}")
    arr = arr[:, :2]
    finite = np.all(np.isfinite(arr), axis=1)
    return arr[finite]


def _crop(xy: np.ndarray, max_range_m: float | None) -> np.ndarray:
    if max_range_m is None:
        return xy
    return xy[np.einsum("ij,ij->i", xy, xy) <= max_range_m**2]


def persistent_points(xy: np.ndarray, min_neighbors: int, radius_m: float) -> np.ndarray:
    """The points with at least ``min_neighbors`` other points within ``radius_m``."""
    if min_neighbors <= 0 or len(xy) == 0:
        return xy
    if len(xy) <= min_neighbors:
        return xy[:0]
    from radarslam.neighbors import GridIndex

    need = min_neighbors + 1  # the point itself is counted
    # A compiled grid count, the same points as a k-d tree's need-th neighbour query at a third
    # of its time on a local map (~9,000 points over 250 m). Cells of twice the radius: finer
    # ones cost more to build (one counter per cell) than they save in distance tests.
    keep = GridIndex(xy, cell_m=2.0 * radius_m).count_within(xy, radius_m, need) >= need
    return xy[keep]


def voxel_downsample_2d(xy: np.ndarray, voxel_m: float) -> np.ndarray:
    """Mean of the points in each occupied square cell."""
    if len(xy) == 0:
        return xy
    cells = np.floor(xy / voxel_m).astype(np.int64)
    # One int64 key per cell: np.unique over rows (axis=0) is ~20x slower than over scalars.
    cells -= cells.min(axis=0)
    keys = cells[:, 0] * (int(cells[:, 1].max()) + 1) + cells[:, 1]
    _, inverse, counts = np.unique(keys, return_inverse=True, return_counts=True)
    out = np.column_stack(
        [np.bincount(inverse, weights=xy[:, k], minlength=len(counts)) for k in range(2)]
    )
    return out / counts[:, None]


def _transform(xy: np.ndarray, pose: np.ndarray) -> np.ndarray:
    return xy @ pose[:2, :2].T + pose[:2, 3]


def _planar(pose: np.ndarray) -> np.ndarray:
    yaw = math.atan2(pose[1, 0], pose[0, 0])
    return se2_to_matrix(float(pose[0, 3]), float(pose[1, 3]), yaw)


@dataclass(frozen=True)
class Hypothesis:
    pose: np.ndarray  # candidate_from_query initial guess
    heading_deg: float
    score: float


class LoopVerifier:
    """Registers a query key frame's local map against a candidate's (see module docstring)."""

    #: Prepared (cropped, filtered, downsampled) maps kept by cache key. In a SLAM run the
    #: nearest key frame of a session stays the proximity candidate of about two consecutive
    #: queries (half the benchmark's verifications repeat a candidate, most within 64 calls).
    cache_size = 64

    def __init__(self, config: LoopVerifierConfig | None = None):
        self.config = config or LoopVerifierConfig()
        self._o3d: Any = None  # the open3d module, imported on first use
        self.log: list[LoopCandidate] = []  # every candidate seen by verify_candidate, in order
        self._prepared_maps: OrderedDict[Hashable, np.ndarray] = OrderedDict()

    @property
    def cached_maps(self) -> int:
        """How many prepared maps the cache holds (at most :attr:`cache_size`)."""
        return len(self._prepared_maps)

    def verify_candidate(
        self,
        query: NodeKey,
        candidate: NodeKey,
        query_timestamp_us: int,
        candidate_timestamp_us: int,
        descriptor_distance: float,
        query_cloud_xy,
        candidate_cloud_xy,
        initial_guess_candidate_from_query: np.ndarray | None = None,
        cache_keys: tuple[Hashable | None, Hashable | None] = (None, None),
    ) -> tuple[LoopCandidate, LoopVerification]:
        """:meth:`verify`, recording the outcome (accepted or not, with the reason) in ``log``."""
        ver = self.verify(
            query_cloud_xy, candidate_cloud_xy, initial_guess_candidate_from_query, cache_keys
        )
        record = LoopCandidate.from_verification(
            query, candidate, query_timestamp_us, candidate_timestamp_us, descriptor_distance, ver
        )
        self.log.append(record)
        return record, ver

    # --- public --------------------------------------------------------------------------------

    def verify(
        self,
        query_cloud_xy,
        candidate_cloud_xy,
        initial_guess_candidate_from_query: np.ndarray | None = None,
        cache_keys: tuple[Hashable | None, Hashable | None] = (None, None),
    ) -> LoopVerification:
        """Register the query's (N, 2) map against the candidate's. ``cache_keys``: for each
        map, a hashable naming its content (same key, same points; None: not cached), so that
        a map verified again skips cropping, filtering and downsampling."""
        t0 = time.perf_counter()
        cfg = self.config
        q = self._prepare(query_cloud_xy, "query cloud", cache_keys[0])
        c = self._prepare(candidate_cloud_xy, "candidate cloud", cache_keys[1])
        guess = np.eye(4)
        if initial_guess_candidate_from_query is not None:
            g = np.asarray(initial_guess_candidate_from_query, dtype=np.float64)
            if g.shape != (4, 4) or not np.all(np.isfinite(g)):
                raise DataError(
                    f"loop verification: initial guess must be a finite 4x4 pose, got {g.shape}"
                )
            guess = _planar(g)
        if len(q) < cfg.min_points or len(c) < cfg.min_points:
            return self._reject(
                f"too few points after downsampling (query {len(q)}, candidate {len(c)}, "
                f"need {cfg.min_points})",
                guess,
                t0,
            )
        from radarslam.neighbors import GridIndex

        # The candidate's, shared by every ICP and scoring below.
        tree = GridIndex(c, cell_m=cfg.max_correspondence_m)
        best = None
        for hyp in self.hypotheses(q, c, guess):
            pose = self.icp(q, c, hyp.pose, tree)
            fitness, rmse, _ = self._score(q, c, pose, cfg.max_correspondence_m, tree)
            key = (fitness, -rmse)
            if best is None or key > best[0]:
                best = (key, pose, fitness, rmse, hyp.heading_deg)
        assert best is not None
        _, pose, fitness, rmse, heading = best
        overlap = self._overlap(q, c, pose)
        # One k-nearest query at the chosen pose serves the tight fitness, the information
        # matrix (nearest neighbours) and the degeneracy test (local line normals).
        moved = _transform(q, pose)
        # Only points with a neighbour within max_correspondence_m enter any of these, so the
        # search may give up on the others (an unbounded search walks far for them).
        dist, idx = tree.query(
            moved,
            min(cfg.normal_neighbors, len(c)),
            nearest_within=np.nextafter(cfg.max_correspondence_m, np.inf),
        )
        tight = float(np.mean(dist[:, 0] <= cfg.tight_correspondence_m))
        inlier = dist[:, 0] <= cfg.max_correspondence_m
        info = self._information(moved[inlier], pose, rmse)
        constraint = _constraint_ratio(c[idx[inlier]])
        reasons = []
        if fitness < cfg.min_fitness:
            reasons.append(f"fitness {fitness:.2f} < {cfg.min_fitness}")
        if not rmse <= cfg.max_inlier_rmse_m:
            reasons.append(f"inlier_rmse {rmse:.2f} m > {cfg.max_inlier_rmse_m}")
        if overlap < cfg.min_overlap:
            reasons.append(f"overlap {overlap:.2f} < {cfg.min_overlap}")
        if tight < cfg.min_tight_fitness:
            reasons.append(f"tight_fitness {tight:.3f} < {cfg.min_tight_fitness}")
        if not constraint >= cfg.min_constraint_ratio:
            reasons.append(f"constraint_ratio {constraint:.2f} < {cfg.min_constraint_ratio}")
        return LoopVerification(
            accepted=not reasons,
            reason="; ".join(reasons) if reasons else "ok",
            candidate_from_query=pose,
            fitness=float(fitness),
            inlier_rmse_m=float(rmse),
            overlap=float(overlap),
            information=info,
            initial_heading_deg=float(heading),
            runtime_ms=(time.perf_counter() - t0) * 1e3,
            tight_fitness=float(tight),
            constraint_ratio=float(constraint),
        )

    # --- stages --------------------------------------------------------------------------------

    def _prepare(self, cloud_xy, what: str, key: Hashable | None) -> np.ndarray:
        if key is not None and key in self._prepared_maps:
            self._prepared_maps.move_to_end(key)
            return self._prepared_maps[key]
        cfg = self.config
        xy = _crop(_as_xy(cloud_xy, what), cfg.max_range_m)
        xy = persistent_points(xy, cfg.min_neighbors, cfg.persistence_radius_m)
        xy = voxel_downsample_2d(xy, cfg.voxel_size_m)
        if key is not None:
            xy.setflags(write=False)  # shared by every later verification under this key
            self._prepared_maps[key] = xy
            while len(self._prepared_maps) > self.cache_size:
                self._prepared_maps.popitem(last=False)
        return xy

    def _reject(self, reason: str, guess: np.ndarray, t0: float) -> LoopVerification:
        nan = float("nan")
        return LoopVerification(
            accepted=False,
            reason=reason,
            candidate_from_query=guess,
            fitness=0.0,
            inlier_rmse_m=nan,
            overlap=0.0,
            information=np.zeros((3, 3)),
            runtime_ms=(time.perf_counter() - t0) * 1e3,
        )

    def hypotheses(self, q: np.ndarray, c: np.ndarray, guess: np.ndarray) -> list[Hypothesis]:
        """The starting poses a verification refines: headings around ``guess`` (the whole
        turn or ``heading_range_deg``), each shifted by the correlative search where it runs
        and only the ``refine_top_k`` best kept."""
        cfg = self.config
        guess_yaw = math.atan2(guess[1, 0], guess[0, 0])
        if cfg.heading_range_deg >= 360.0:
            steps = max(1, round(360.0 / cfg.heading_step_deg))
            offsets = [n * 360.0 / steps for n in range(steps)]
        else:
            half = int(cfg.heading_range_deg / 2 // cfg.heading_step_deg)
            offsets = [n * cfg.heading_step_deg % 360.0 for n in range(-half, half + 1)]
        poses, headings = [], []
        for dh in offsets:
            yaw = guess_yaw + math.radians(dh)
            poses.append(se2_to_matrix(guess[0, 3], guess[1, 3], yaw))
            headings.append(dh if dh <= 180 else dh - 360)
        scores = [0.0] * len(poses)
        grid = None
        if cfg.correlative_search and cfg.search_radius_m > 0:
            grid = _LikelihoodGrid(c, cfg.grid_cell_m)
            found = grid.best_shifts([_transform(q, p) for p in poses], cfg.search_radius_m)
            for pose, (shift, _) in zip(poses, found, strict=True):
                pose[:2, 3] += shift
            scores = [score for _, score in found]
        hyps = [Hypothesis(p, h, sc) for p, h, sc in zip(poses, headings, scores, strict=True)]
        if grid is not None:
            hyps.sort(key=lambda h: -h.score)
            hyps = hyps[: cfg.refine_top_k]
        return hyps

    def icp(self, q: np.ndarray, c: np.ndarray, init: np.ndarray, tree=None) -> np.ndarray:
        """candidate_from_query refined from ``init`` by the configured backend (``tree``: a
        prepared :class:`~radarslam.neighbors.GridIndex` of ``c`` for the grid backend)."""
        cfg = self.config
        pose = init
        # The coarse stage aligns a strided subset; the fine one, whose pose is scored, all points.
        sub = q[:: math.ceil(len(q) / cfg.max_icp_points)] if len(q) > cfg.max_icp_points else q
        for src, max_corr in (
            (sub, cfg.coarse_max_correspondence_m),
            (q, cfg.max_correspondence_m),
        ):
            if cfg.backend == "grid":
                if tree is None:
                    from radarslam.neighbors import GridIndex

                    tree = GridIndex(c, cell_m=cfg.max_correspondence_m)
                pose = tree.icp_point_to_point(
                    src,
                    pose,
                    max_corr,
                    cfg.icp_relative_tolerance,
                    cfg.icp_relative_tolerance,
                    cfg.max_iterations,
                )
            else:
                pose = self.icp_open3d(src, c, pose, max_corr)
            pose = _planar(pose)
        return pose

    def icp_open3d(self, q, c, init, max_corr) -> np.ndarray:
        """One point-to-point ICP stage by open3d (the reference the grid backend replays)."""
        if self._o3d is None:
            import open3d as o3d

            o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
            self._o3d = o3d
        o3d = self._o3d
        reg = o3d.pipelines.registration

        def cloud(xy):
            return o3d.geometry.PointCloud(
                o3d.utility.Vector3dVector(np.column_stack([xy, np.zeros(len(xy))]))
            )

        res = reg.registration_icp(
            cloud(q),
            cloud(c),
            max_corr,
            init,
            reg.TransformationEstimationPointToPoint(),
            reg.ICPConvergenceCriteria(
                relative_fitness=self.config.icp_relative_tolerance,
                relative_rmse=self.config.icp_relative_tolerance,
                max_iteration=self.config.max_iterations,
            ),
        )
        return np.asarray(res.transformation, dtype=np.float64)

    def _score(self, q, c, pose, max_corr, tree=None):
        if tree is None:
            from radarslam.neighbors import GridIndex

            tree = GridIndex(c, cell_m=self.config.max_correspondence_m)
        moved = _transform(q, pose)
        d, idx = tree.query(moved, 1, max_corr)
        d, idx = d[:, 0], idx[:, 0]
        ok = np.isfinite(d)
        fitness = float(ok.mean())
        rmse = float(np.sqrt(np.mean(d[ok] ** 2))) if ok.any() else float("inf")
        return fitness, rmse, (moved[ok], c[idx[ok]])

    def _overlap(self, q, c, pose) -> float:
        """Shared occupied cells / the smaller map's occupied cells, in the candidate frame."""
        cell = self.config.overlap_cell_m
        qc = np.floor(_transform(q, pose) / cell).astype(np.int64)
        cc = np.floor(c / cell).astype(np.int64)
        lo = np.minimum(qc.min(axis=0), cc.min(axis=0))
        width = int(max(qc[:, 1].max(), cc[:, 1].max()) - lo[1]) + 1

        def keys(cells):
            return np.unique((cells[:, 0] - lo[0]) * width + (cells[:, 1] - lo[1]))

        kq, kc = keys(qc), keys(cc)
        shared = len(np.intersect1d(kq, kc, assume_unique=True))
        return shared / max(1, min(len(kq), len(kc)))

    def _information(self, moved: np.ndarray, pose: np.ndarray, rmse: float) -> np.ndarray:
        """Point-to-point Hessian (left perturbation in the candidate frame) of the aligned query
        points ``moved`` that have a correspondence, scaled by the inlier RMSE, plus the floor
        covariance, then moved to gtsam's right perturbation of the ``candidate_from_query``
        measurement."""
        cfg = self.config
        if len(moved) < 3:
            return np.zeros((3, 3))
        # d(p')/d(tx, ty, theta) for p' = exp(xi) p: [[1, 0, -y], [0, 1, x]]
        n = len(moved)
        h = np.zeros((3, 3))
        h[0, 0] = h[1, 1] = n
        h[0, 2] = h[2, 0] = -moved[:, 1].sum()
        h[1, 2] = h[2, 1] = moved[:, 0].sum()
        h[2, 2] = float(np.sum(moved**2))
        sigma = max(float(rmse), cfg.min_sigma_m)
        try:
            cov_left = np.linalg.inv(h / sigma**2)
        except np.linalg.LinAlgError:
            return np.zeros((3, 3))
        # xi_left = Ad(T) xi_right  =>  cov_right = Ad(T)^-1 cov_left Ad(T)^-T
        x, y = pose[0, 3], pose[1, 3]
        cs, sn = pose[0, 0], pose[1, 0]
        ad = np.array([[cs, -sn, y], [sn, cs, -x], [0.0, 0.0, 1.0]])
        ad_inv = np.linalg.inv(ad)
        cov = ad_inv @ cov_left @ ad_inv.T
        yaw_floor = math.radians(cfg.floor_sigma_yaw_deg)
        floor = np.diag([cfg.floor_sigma_xy_m**2, cfg.floor_sigma_xy_m**2, yaw_floor**2])
        info = np.linalg.inv(cov + floor)
        return 0.5 * (info + info.T)


def _constraint_ratio(neighbours: np.ndarray) -> float:
    """Smaller / larger eigenvalue of sum(n n^T) over point-to-line normals, one per (k, 2) set of
    ``neighbours`` (a correspondence's nearest candidate points); 0 with fewer than 3: nothing is
    constrained."""
    if len(neighbours) < 3 or neighbours.shape[1] < 2:
        return 0.0
    centred = neighbours - neighbours.mean(axis=1, keepdims=True)
    sxx = np.einsum("mk,mk->m", centred[..., 0], centred[..., 0])
    syy = np.einsum("mk,mk->m", centred[..., 1], centred[..., 1])
    sxy = np.einsum("mk,mk->m", centred[..., 0], centred[..., 1])
    # With a unit normal at angle phi, n n^T = (I + [[cos 2phi, sin 2phi], [sin 2phi, -cos 2phi]])
    # / 2, so sum(n n^T) has eigenvalues (N -+ R) / 2 with R = |sum e^(2i phi)|, and e^(2i phi) is
    # minus the direction of the scatter's (sxx - syy, 2 sxy): no eigen-solver per point needed.
    z = (sxx - syy) + 2j * sxy
    mag = np.abs(z)
    line = mag > 0  # an isotropic neighbourhood has no line direction: it adds to N, not to R
    r = float(np.abs(np.sum(z[line] / mag[line])))
    n = float(len(neighbours))
    return (n - r) / (n + r)


class _LikelihoodGrid:
    """The candidate map as a blurred occupancy grid, for FFT translation search."""

    #: Blur weights of a cell and of its 4 side neighbours. Every score is a sum of them, so a
    #: multiple of ``_QUANTUM``, which lets the search compare scores exactly.
    _CENTRE, _SIDE = 1.0, 0.5
    _QUANTUM = 0.5

    def __init__(self, c: np.ndarray, cell_m: float):
        self.cell = cell_m
        self.origin = c.min(axis=0)
        idx = np.floor((c - self.origin) / cell_m).astype(np.int64)
        shape = idx.max(axis=0) + 1
        occ = np.zeros(shape)
        occ[idx[:, 0], idx[:, 1]] = 1.0
        # 3x3 blur: tolerate sub-cell misalignment without rewarding vague matches too much
        pad = np.pad(occ, 1)
        blur = sum(
            pad[1 + dx : 1 + dx + shape[0], 1 + dy : 1 + dy + shape[1]] * w
            for dx, dy, w in [(0, 0, self._CENTRE)]
            + [(a, b, self._SIDE) for a, b in ((1, 0), (-1, 0), (0, 1), (0, -1))]
        )
        self.grid: np.ndarray = np.asarray(blur)  # the sum's type is ndarray | int to mypy

    def best_shifts(
        self, queries: list[np.ndarray], radius_m: float
    ) -> list[tuple[np.ndarray, float]]:
        """For each query (points in the candidate frame), the translation (2,) within
        +-radius_m maximising the summed grid likelihood, and that score normalised by the
        query's occupied cells; of equal scores, the smallest translation. One FFT of the grid
        serves every query (heading hypotheses)."""
        from scipy import fft

        r = math.ceil(radius_m / self.cell)
        cells = [np.floor((q - self.origin) / self.cell).astype(np.int64) for q in queries]
        # Only the grid under the queries, widened by the search radius, can score: the FFTs
        # span that window, not grid and query side by side (3-4x fewer cells for a local map).
        lo = np.min([qi.min(axis=0) for qi in cells], axis=0) - r
        hi = np.max([qi.max(axis=0) for qi in cells], axis=0) + r
        full = tuple(fft.next_fast_len(int(n), real=True) for n in hi - lo + 1)
        window = np.zeros(full, dtype=np.float32)  # float32: 2x faster FFTs
        g0 = np.maximum(lo, 0)
        g1 = np.minimum(hi + 1, self.grid.shape)
        if np.all(g1 > g0):
            window[g0[0] - lo[0] : g1[0] - lo[0], g0[1] - lo[1] : g1[1] - lo[1]] = self.grid[
                g0[0] : g1[0], g0[1] : g1[1]
            ]
        qocc = np.zeros((len(cells), *full), dtype=np.float32)
        for k, qi in enumerate(cells):
            qocc[k, qi[:, 0] - lo[0] - r, qi[:, 1] - lo[1] - r] = 1.0
        # corr[k, s + r] = sum_u qocc(u) window(u + s + r): the score of shift s. Circular over
        # `full`, but u + s + r stays inside the window, so nothing wraps around.
        spec = fft.rfft2(window)[None] * np.conj(fft.rfft2(qocc, axes=(-2, -1)))
        corr = fft.irfft2(spec, full, axes=(-2, -1))[:, : 2 * r + 1, : 2 * r + 1]
        # Scores are multiples of the blur's quantum: rounded to it, ties are exact and go to the
        # shift nearest the initial guess rather than to the FFT's rounding noise.
        steps = np.rint(corr / self._QUANTUM)
        sx = np.arange(-r, r + 1)
        dist2 = (sx[:, None] ** 2 + sx[None, :] ** 2).astype(np.float64)
        out = []
        for k in range(len(cells)):
            best = steps[k] == steps[k].max()
            ij = np.unravel_index(int(np.argmin(np.where(best, dist2, np.inf))), best.shape)
            shift = np.array([sx[ij[0]], sx[ij[1]]], dtype=np.float64) * self.cell
            occupied = max(1.0, float(qocc[k].sum()))
            out.append((shift, float(steps[k][ij]) * self._QUANTUM / occupied))
        return out
