"""Multi-session pose graph over GTSAM: iSAM2 while driving, a final batch LM (optionally GNC).

Nodes are key frames, addressed by :class:`~radarslam.io.loops.NodeKey` ``(session, index)``.
Each session (nuScenes scene) is its own odometry chain, or goes on from the chain of the scene
it continues (:meth:`PoseGraph.add_continuation`). A session added with ``anchor="prior"``
(the first) is pinned by a tight prior at its first pose guess; a session added with
``anchor="unknown"`` gets a *weak* prior (``unknown_anchor_sigmas``, default 100 m / pi) at its
first pose guess: it keeps the problem well posed while the session floats, and it is negligible
(information ratio ~1e-6) as soon as loop closures tie the session to the others. A session never
joined by a loop or a continuation therefore stays where its guess put it and is reported as its
own component by :meth:`PoseGraph.components` instead of being silently forced onto the others.

GTSAM key scheme: ``gtsam.symbol('x', (session_ordinal << 32) | index)`` where
``session_ordinal`` counts sessions in the order they were added (``Symbol(k).string()`` reads
``x<number>``; :meth:`PoseGraph.node_key` maps back).

Tangent orders (GTSAM's): Pose2 is (x, y, theta); Pose3 is (rx, ry, rz, tx, ty, tz).
Covariances and information matrices passed in are always planar 3x3 in Pose2 order (x, y, yaw);
with ``pose_type="pose3"`` they are embedded into 6x6 with tight z / roll / pitch sigmas.

Robust kernels and iSAM2: a robust loop factor that arrives while drift is large stays down-weighted
in iSAM2's cached linearisation, so :meth:`optimize_batch` (LM from the iSAM2 estimate, then LM with
a redescending Geman-McClure kernel on the loops from the better of two starts) should run at
the end of a run; :meth:`estimate` returns whichever solve is newest.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import Field

from radarslam.config import StrictModel
from radarslam.errors import ConfigError, DataError
from radarslam.geometry import matrix_to_se2, rotation_to_quat
from radarslam.io.atomic import atomic_open
from radarslam.io.loops import NodeKey

RobustKind = Literal["cauchy", "huber", "none"]


class Isam2Config(StrictModel):
    relinearize_threshold: float = Field(0.1, gt=0)
    relinearize_skip: int = Field(1, ge=1)
    # extra iSAM2 iterations after an update that brought a loop closure (large correction)
    extra_iterations_after_loop: int = Field(2, ge=0)


class BatchConfig(StrictModel):
    max_iterations: int = Field(100, ge=1)
    relative_error_tol: float = Field(1e-5, gt=0)
    absolute_error_tol: float = Field(1e-5, ge=0)


class PoseGraphConfig(StrictModel):
    pose_type: Literal["pose2", "pose3"] = "pose2"
    incremental: bool = True  # feed iSAM2 on every update(); False: only batch solves
    prior_sigmas: tuple[float, float, float] = (0.01, 0.01, 0.001)  # m, m, rad
    unknown_anchor_sigmas: tuple[float, float, float] = (100.0, 100.0, math.pi)
    pose3_planar_sigmas: tuple[float, float] = (0.01, 0.001)  # z (m), roll/pitch (rad)
    loop_robust: RobustKind = "cauchy"
    loop_robust_param: float = Field(1.0, gt=0)
    # chi2 (3 dof) above which an optimised loop counts as an outlier in loop_residuals/components
    loop_inlier_chi2: float = Field(11.345, gt=0)
    isam2: Isam2Config = Isam2Config()
    batch: BatchConfig = BatchConfig()
    # A second batch solve with a redescending kernel on the loops.
    # A Cauchy loop still pulls with a force that falls off only as 1 / error, so hundreds of
    # false loops tens of metres long add up; Geman-McClure's falls off as 1 / error^3. It is
    # non-convex, so it starts from both the first solve's result and the estimate before it
    # and keeps the solution of least cost. The parameter is in whitened units (a loop's
    # sigma, >= 0.1 m): with 5, a loop 3 sigma off keeps half its weight, one 50 m off none.
    # "none": off.
    final_robust: Literal["none", "geman_mcclure"] = "geman_mcclure"
    final_robust_param: float = Field(5.0, gt=0)


@dataclass(frozen=True)
class GraphComponent:
    """Sessions connected through loop closures (union-find over sessions)."""

    sessions: tuple[str, ...]
    anchored: bool  # contains the session pinned by the tight prior
    anchor_session: str  # the prior-anchored session, or the first-added session of the group


@dataclass(frozen=True)
class LoopResidual:
    key_a: NodeKey
    key_b: NodeKey
    chi2: float  # r^T Info r of the loop's Gaussian part at the current estimate
    inlier: bool


@dataclass(frozen=True)
class _LoopRecord:
    key_a: NodeKey
    key_b: NodeKey
    a_from_b: np.ndarray
    information: np.ndarray
    factor_index: int  # index in the full graph


def _check_matrix3(m, what: str, positive_definite: bool = True) -> np.ndarray:
    arr = np.asarray(m, dtype=np.float64)
    if arr.shape != (3, 3):
        raise DataError(f"{what}: expected a 3x3 matrix, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise DataError(f"{what}: non-finite entries")
    if not np.allclose(arr, arr.T, rtol=1e-6, atol=1e-12 * max(1.0, np.abs(arr).max())):
        raise DataError(f"{what}: not symmetric")
    arr = 0.5 * (arr + arr.T)
    if positive_definite and np.linalg.eigvalsh(arr)[0] <= 0:
        raise DataError(f"{what}: not positive definite (eigenvalues {np.linalg.eigvalsh(arr)})")
    return arr


def _check_pose(pose, what: str) -> np.ndarray:
    arr = np.asarray(pose, dtype=np.float64)
    if arr.shape != (4, 4) or not np.all(np.isfinite(arr)):
        raise DataError(f"{what}: expected a finite 4x4 pose, got shape {arr.shape}")
    return arr


class PoseGraph:
    """Incremental multi-session pose graph (see the module docstring for conventions)."""

    def __init__(self, config: PoseGraphConfig | None = None):
        import gtsam

        self._g = gtsam
        self.config = config or PoseGraphConfig()
        self._pose3 = self.config.pose_type == "pose3"
        self._sessions: dict[str, int] = {}  # session -> ordinal
        self._session_anchor: dict[str, str] = {}  # session -> "prior" | "unknown"
        self._session_sizes: dict[str, int] = {}
        self._keys: list[NodeKey] = []  # insertion order
        self._known: set[NodeKey] = set()
        self._graph = gtsam.NonlinearFactorGraph()  # every factor ever added
        self._initial = gtsam.Values()  # every initial guess ever made
        self._new_graph = gtsam.NonlinearFactorGraph()
        self._new_values = gtsam.Values()
        self._new_has_loop = False
        self._loops: list[_LoopRecord] = []
        self._odometry_edges: list[tuple[NodeKey, NodeKey, np.ndarray, np.ndarray]] = []
        self._continuations: list[tuple[NodeKey, NodeKey]] = []
        self._isam = None
        if self.config.incremental:
            p = gtsam.ISAM2Params()
            p.setRelinearizeThreshold(self.config.isam2.relinearize_threshold)
            p.relinearizeSkip = self.config.isam2.relinearize_skip
            # QR, not Cholesky: a later session's weak anchor (100 m, pi) beside radar odometry
            # at millimetre level spans ~1e9 in information, which Cholesky reports as an
            # indeterminate system.
            p.setFactorization("QR")
            self._isam = gtsam.ISAM2(p)
        self._isam_fed = False
        self._batch_result = None  # gtsam.Values of the newest batch solve
        self._newest = "initial"  # which estimate is newest: "initial" | "isam" | "batch"
        self.update_times_s: list[float] = []
        self.last_batch_iterations = 0
        self.last_batch_time_s = 0.0

    # --- keys ----------------------------------------------------------------------------------

    def gtsam_key(self, key: NodeKey) -> int:
        try:
            ordinal = self._sessions[key.session]
        except KeyError:
            raise DataError(f"pose graph: unknown session {key.session!r}") from None
        if not 0 <= key.index < (1 << 32):
            raise DataError(f"pose graph: key frame index {key.index} out of range")
        return self._g.symbol("x", (ordinal << 32) | key.index)

    def node_key(self, gtsam_key: int) -> NodeKey:
        index = self._g.Symbol(gtsam_key).index()
        ordinal, i = index >> 32, index & 0xFFFFFFFF
        for name, o in self._sessions.items():
            if o == ordinal:
                return NodeKey(name, int(i))
        raise DataError(f"pose graph: gtsam key {gtsam_key} belongs to no session")

    @property
    def sessions(self) -> list[str]:
        return list(self._sessions)

    @property
    def keys(self) -> list[NodeKey]:
        return list(self._keys)

    @property
    def num_loops(self) -> int:
        return len(self._loops)

    def __contains__(self, key: NodeKey) -> bool:
        return key in self._known

    # --- gtsam conversions ---------------------------------------------------------------------

    def _to_gtsam(self, pose: np.ndarray):
        if self._pose3:
            return self._g.Pose3(np.asarray(pose, dtype=np.float64))
        x, y, yaw = matrix_to_se2(pose)
        return self._g.Pose2(float(x), float(y), float(yaw))

    def _from_gtsam(self, obj) -> np.ndarray:
        m = np.asarray(obj.matrix(), dtype=np.float64)
        if self._pose3:
            return m
        out = np.eye(4)
        out[:2, :2] = m[:2, :2]
        out[:2, 3] = m[:2, 2]
        return out

    def _value(self, values, k: int):
        return values.atPose3(k) if self._pose3 else values.atPose2(k)

    def _embed(self, planar: np.ndarray, is_information: bool) -> np.ndarray:
        """3x3 (x, y, yaw) -> the pose type's tangent order."""
        if not self._pose3:
            return planar
        z_m, rp_rad = self.config.pose3_planar_sigmas
        diag = [rp_rad**2, rp_rad**2, 0, 0, 0, z_m**2]
        if is_information:
            diag = [1 / d if d else 0.0 for d in diag]
        out = np.diag(diag).astype(np.float64)
        idx = [3, 4, 2]  # Pose3 tangent is (rx, ry, rz, tx, ty, tz)
        out[np.ix_(idx, idx)] = planar
        return out

    def _noise_from_covariance(self, cov: np.ndarray):
        return self._g.noiseModel.Gaussian.Covariance(self._embed(cov, False))

    def _noise_from_information(self, info: np.ndarray):
        return self._g.noiseModel.Gaussian.Information(self._embed(info, True))

    def _robust(self, base, robust: RobustKind):
        if robust == "none":
            return base
        m = self._g.noiseModel.mEstimator
        k = self.config.loop_robust_param
        est = m.Cauchy.Create(k) if robust == "cauchy" else m.Huber.Create(k)
        return self._g.noiseModel.Robust.Create(est, base)

    def _prior_factor(self, k, pose, noise):
        cls = self._g.PriorFactorPose3 if self._pose3 else self._g.PriorFactorPose2
        return cls(k, self._to_gtsam(pose), noise)

    def _between_factor(self, ka, kb, a_from_b, noise):
        cls = self._g.BetweenFactorPose3 if self._pose3 else self._g.BetweenFactorPose2
        return cls(ka, kb, self._to_gtsam(a_from_b), noise)

    def _add_factor(self, factor) -> int:
        index = self._graph.size()
        self._graph.add(factor)
        self._new_graph.add(factor)
        return index

    def _add_node(self, key: NodeKey, world_from_ego: np.ndarray) -> None:
        k = self.gtsam_key(key)
        value = self._to_gtsam(world_from_ego)
        self._initial.insert(k, value)
        self._new_values.insert(k, value)
        self._keys.append(key)
        self._known.add(key)
        self._session_sizes[key.session] = max(self._session_sizes[key.session], key.index + 1)

    # --- building ------------------------------------------------------------------------------

    def add_session(
        self,
        session_id: str,
        first_pose_guess: np.ndarray,
        anchor: Literal["prior", "unknown"] = "unknown",
    ) -> NodeKey:
        """Start a session: node ``(session_id, 0)`` at ``first_pose_guess`` (world_from_ego)."""
        if session_id in self._sessions:
            raise DataError(f"pose graph: session {session_id!r} added twice")
        if anchor not in ("prior", "unknown"):
            raise ConfigError(f"pose graph: anchor must be 'prior' or 'unknown', got {anchor!r}")
        pose = _check_pose(first_pose_guess, f"session {session_id!r} first pose guess")
        self._sessions[session_id] = len(self._sessions)
        self._session_anchor[session_id] = anchor
        self._session_sizes[session_id] = 0
        key = NodeKey(session_id, 0)
        self._add_node(key, pose)
        sigmas = (
            self.config.prior_sigmas if anchor == "prior" else self.config.unknown_anchor_sigmas
        )
        cov = np.diag(np.square(np.asarray(sigmas, dtype=np.float64)))
        self._add_factor(
            self._prior_factor(self.gtsam_key(key), pose, self._noise_from_covariance(cov))
        )
        return key

    def add_odometry(
        self,
        session_id: str,
        i: int,
        j: int,
        relative_pose: np.ndarray,
        covariance_3x3: np.ndarray,
    ) -> NodeKey:
        """Odometry ``ego_i_from_ego_j`` with its (x, y, yaw) covariance; creates node j if new,
        initialised by composing the current estimate of node i with the measurement."""
        ki, kj = NodeKey(session_id, int(i)), NodeKey(session_id, int(j))
        if session_id not in self._sessions:
            raise DataError(f"pose graph: odometry for unknown session {session_id!r}")
        if ki not in self._known:
            raise DataError(f"pose graph: odometry from missing node {ki}")
        rel = _check_pose(relative_pose, f"odometry {ki}->{kj}")
        cov = _check_matrix3(covariance_3x3, f"odometry {ki}->{kj} covariance")
        if kj not in self._known:
            self._add_node(kj, self.current_pose(ki) @ rel)
        factor = self._between_factor(
            self.gtsam_key(ki), self.gtsam_key(kj), rel, self._noise_from_covariance(cov)
        )
        self._add_factor(factor)
        self._odometry_edges.append((ki, kj, rel, cov))
        return kj

    def add_continuation(
        self,
        key_a: NodeKey,
        key_b: NodeKey,
        relative_pose: np.ndarray,
        covariance_3x3: np.ndarray,
    ) -> None:
        """Odometry ``a_from_b`` from the last node of one session to the first of a session that
        continues its drive (both nodes exist); the two sessions are one component."""
        for key in (key_a, key_b):
            if key not in self._known:
                raise DataError(f"pose graph: continuation to missing node {key}")
        if key_a.session == key_b.session:
            raise DataError(f"pose graph: continuation {key_a}->{key_b} inside one session")
        rel = _check_pose(relative_pose, f"continuation {key_a}->{key_b}")
        cov = _check_matrix3(covariance_3x3, f"continuation {key_a}->{key_b} covariance")
        self._add_factor(
            self._between_factor(
                self.gtsam_key(key_a), self.gtsam_key(key_b), rel, self._noise_from_covariance(cov)
            )
        )
        self._odometry_edges.append((key_a, key_b, rel, cov))
        self._continuations.append((key_a, key_b))

    def add_loop(
        self,
        key_a: NodeKey,
        key_b: NodeKey,
        relative_pose: np.ndarray,
        information_3x3: np.ndarray,
        robust: RobustKind | None = None,
    ) -> int:
        """Loop closure measuring ``a_from_b`` (pose of b in a's frame); ``robust`` defaults to the
        config kernel (``"none"`` for a plain Gaussian). Returns the loop's index."""
        for key in (key_a, key_b):
            if key not in self._known:
                raise DataError(f"pose graph: loop closure to missing node {key}")
        if key_a == key_b:
            raise DataError(f"pose graph: loop closure from {key_a} to itself")
        rel = _check_pose(relative_pose, f"loop {key_a}->{key_b}")
        info = _check_matrix3(information_3x3, f"loop {key_a}->{key_b} information")
        kind = self.config.loop_robust if robust is None else robust
        if kind not in ("cauchy", "huber", "none"):
            raise ConfigError(f"pose graph: unknown robust kernel {kind!r}")
        noise = self._robust(self._noise_from_information(info), kind)
        index = self._add_factor(
            self._between_factor(self.gtsam_key(key_a), self.gtsam_key(key_b), rel, noise)
        )
        self._loops.append(_LoopRecord(key_a, key_b, rel, info, index))
        self._new_has_loop = True
        return len(self._loops) - 1

    # --- solving -------------------------------------------------------------------------------

    def update(self) -> float:
        """Feed iSAM2 the factors and values added since the last update; returns seconds spent."""
        t0 = time.perf_counter()
        if self._isam is not None and (self._new_graph.size() or self._new_values.size()):
            self._isam.update(self._new_graph, self._new_values)
            if self._new_has_loop:
                for _ in range(self.config.isam2.extra_iterations_after_loop):
                    self._isam.update()
            self._isam_fed = True
            self._newest = "isam"
        self._new_graph = self._g.NonlinearFactorGraph()
        self._new_values = self._g.Values()
        self._new_has_loop = False
        dt = time.perf_counter() - t0
        self.update_times_s.append(dt)
        return dt

    def _current_values(self):
        """Best available Values for every node (newest solve, initial guesses for the rest)."""
        if self._newest == "batch" and self._batch_result is not None:
            base = self._batch_result
        elif self._newest == "isam" and self._isam_fed:
            base = self._isam.calculateEstimate()
        else:
            return self._initial
        if base.size() == self._initial.size():
            return base
        merged = self._g.Values(base)
        for k in self._initial.keys():
            if not merged.exists(k):
                merged.insert(k, self._value(self._initial, k))
        return merged

    def current_pose(self, key: NodeKey) -> np.ndarray:
        """Newest estimate of one node (cheap: no full read-out of iSAM2)."""
        k = self.gtsam_key(key)
        if key not in self._known:
            raise DataError(f"pose graph: no node {key}")
        if self._newest == "batch" and self._batch_result is not None:
            if self._batch_result.exists(k):
                return self._from_gtsam(self._value(self._batch_result, k))
        elif self._newest == "isam" and self._isam_fed and self._isam.valueExists(k):
            est = (
                self._isam.calculateEstimatePose3(k)
                if self._pose3
                else self._isam.calculateEstimatePose2(k)
            )
            return self._from_gtsam(est)
        return self._from_gtsam(self._value(self._initial, k))

    def optimize_batch(self) -> dict[NodeKey, np.ndarray]:
        """Levenberg-Marquardt on the whole graph from the newest estimate, then the
        redescending solve; returns :meth:`estimate`."""
        self.update()
        g = self._g
        t0 = time.perf_counter()
        start = self._current_values()
        p = g.LevenbergMarquardtParams()
        p.setLinearSolverType("MULTIFRONTAL_QR")  # same conditioning reason as iSAM2
        p.setMaxIterations(self.config.batch.max_iterations)
        p.setRelativeErrorTol(self.config.batch.relative_error_tol)
        p.setAbsoluteErrorTol(self.config.batch.absolute_error_tol)
        opt = g.LevenbergMarquardtOptimizer(self._graph, start, p)
        result = opt.optimize()
        self.last_batch_iterations = int(opt.iterations())
        if self.config.final_robust != "none" and self._loops:
            result = self._redescending_solve((start, result), p)
        self._batch_result = result
        self._newest = "batch"
        self.last_batch_time_s = time.perf_counter() - t0
        return self.estimate()

    def _redescending_solve(self, starts, params):
        """LM on a copy of the graph whose loop factors carry the ``final_robust`` kernel (the
        graph itself keeps its kernels: iSAM2 and later solves go on from the same factors),
        from each of ``starts``; the solution of least cost. A redescending kernel keeps the
        basin it starts in: the first solve's may be one that many false loops pulled a
        weakly linked session into, the newest estimate before it another."""
        g = self._g
        est = g.noiseModel.mEstimator.GemanMcClure.Create(self.config.final_robust_param)
        graph = g.NonlinearFactorGraph(self._graph)
        for rec in self._loops:
            noise = g.noiseModel.Robust.Create(est, self._noise_from_information(rec.information))
            factor = self._between_factor(
                self.gtsam_key(rec.key_a), self.gtsam_key(rec.key_b), rec.a_from_b, noise
            )
            graph.replace(rec.factor_index, factor)
        best = None
        for start in starts:
            opt = g.LevenbergMarquardtOptimizer(graph, start, params)
            result = opt.optimize()
            self.last_batch_iterations += int(opt.iterations())
            cost = graph.error(result)
            if best is None or cost < best[0]:
                best = (cost, result)
        return best[1]

    # --- read-out ------------------------------------------------------------------------------

    def estimate(self) -> dict[NodeKey, np.ndarray]:
        """Newest estimate of every node as 4x4 ``world_from_ego``."""
        values = self._current_values()
        return {
            key: self._from_gtsam(self._value(values, self.gtsam_key(key))) for key in self._keys
        }

    def session_poses(self, session_id: str) -> np.ndarray:
        """(N, 4, 4) newest estimate of one session's key frames, by index."""
        if session_id not in self._sessions:
            raise DataError(f"pose graph: unknown session {session_id!r}")
        values = self._current_values()
        keys = sorted(k for k in self._keys if k.session == session_id)
        return np.stack([self._from_gtsam(self._value(values, self.gtsam_key(k))) for k in keys])

    def marginal_covariance(self, key: NodeKey) -> np.ndarray:
        """Marginal covariance of a node in the pose type's tangent order (Pose2: x, y, theta;
        Pose3: rx, ry, rz, tx, ty, tz), from the newest solve."""
        if key not in self._known:
            raise DataError(f"pose graph: no node {key}")
        self.update()
        k = self.gtsam_key(key)
        if self._newest == "batch" and self._batch_result is not None:
            return np.asarray(
                self._g.Marginals(self._graph, self._batch_result).marginalCovariance(k)
            )
        if self._isam_fed:
            return np.asarray(self._isam.marginalCovariance(k))
        return np.asarray(self._g.Marginals(self._graph, self._initial).marginalCovariance(k))

    def loop_residuals(self) -> list[LoopResidual]:
        """Chi2 of every loop's Gaussian part at the newest estimate; above ``loop_inlier_chi2``
        the loop disagrees with the rest of the graph (an outlier the kernel down-weighted)."""
        values = self._current_values()
        out = []
        for rec in self._loops:
            f = self._between_factor(
                self.gtsam_key(rec.key_a),
                self.gtsam_key(rec.key_b),
                rec.a_from_b,
                self._noise_from_information(rec.information),
            )
            chi2 = 2.0 * float(f.error(values))
            out.append(
                LoopResidual(rec.key_a, rec.key_b, chi2, chi2 <= self.config.loop_inlier_chi2)
            )
        return out

    def components(self, inliers_only: bool = False) -> list[GraphComponent]:
        """Groups of sessions joined by loop closures or continuations (union-find). With
        ``inliers_only`` only loops that agree with the newest estimate count. Anchored
        component first."""
        parent = {s: s for s in self._sessions}

        def find(s: str) -> str:
            while parent[s] != s:
                parent[s] = parent[parent[s]]
                s = parent[s]
            return s

        residuals = self.loop_residuals() if inliers_only else None
        joins = [
            (rec.key_a.session, rec.key_b.session)
            for n, rec in enumerate(self._loops)
            if residuals is None or residuals[n].inlier
        ]
        joins += [(ka.session, kb.session) for ka, kb in self._continuations]
        for sa, sb in joins:
            a, b = find(sa), find(sb)
            if a != b:
                # keep the earlier-added session as the root: it names the component
                if self._sessions[a] < self._sessions[b]:
                    parent[b] = a
                else:
                    parent[a] = b
        groups: dict[str, list[str]] = {}
        for s in self._sessions:
            groups.setdefault(find(s), []).append(s)
        comps = []
        for root, members in groups.items():
            anchored = [s for s in members if self._session_anchor[s] == "prior"]
            comps.append(
                GraphComponent(tuple(members), bool(anchored), anchored[0] if anchored else root)
            )
        comps.sort(key=lambda c: (not c.anchored, self._sessions[c.sessions[0]]))
        return comps

    # --- export --------------------------------------------------------------------------------

    def export_g2o(self, path: str | Path) -> None:
        """Write nodes and odometry/loop edges (newest estimate) in g2o format, atomically.

        Vertex ids are dense, in node insertion order (``self.keys``). Pose2 writes VERTEX_SE2 /
        EDGE_SE2 (information upper triangle in x, y, theta order); Pose3 writes VERTEX_SE3:QUAT /
        EDGE_SE3:QUAT (g2o orders information translation first). Priors and robust kernels have no
        g2o form and are not written.
        """
        values = self._current_values()
        ids = {key: n for n, key in enumerate(self._keys)}
        edges = [(a, b, rel, np.linalg.inv(cov)) for a, b, rel, cov in self._odometry_edges]
        edges += [(r.key_a, r.key_b, r.a_from_b, r.information) for r in self._loops]
        with atomic_open(path, "w") as fh:
            for key in self._keys:
                pose = self._from_gtsam(self._value(values, self.gtsam_key(key)))
                fh.write(self._g2o_vertex(ids[key], pose) + "\n")
            for a, b, rel, info in edges:
                fh.write(self._g2o_edge(ids[a], ids[b], rel, info) + "\n")

    def _g2o_vertex(self, vid: int, pose: np.ndarray) -> str:
        if not self._pose3:
            x, y, yaw = matrix_to_se2(pose)
            return f"VERTEX_SE2 {vid} " + " ".join(repr(float(v)) for v in (x, y, yaw))
        w, qx, qy, qz = rotation_to_quat(pose[:3, :3])
        t = pose[:3, 3]
        nums = [*t, qx, qy, qz, w]
        return f"VERTEX_SE3:QUAT {vid} " + " ".join(repr(float(v)) for v in nums)

    def _g2o_edge(self, va: int, vb: int, rel: np.ndarray, info3: np.ndarray) -> str:
        if not self._pose3:
            x, y, yaw = matrix_to_se2(rel)
            upper = [info3[r, c] for r in range(3) for c in range(r, 3)]
            nums = [x, y, yaw, *upper]
            return f"EDGE_SE2 {va} {vb} " + " ".join(repr(float(v)) for v in nums)
        info6 = self._embed(info3, True)
        order = [3, 4, 5, 0, 1, 2]  # gtsam (r, t) -> g2o (t, r)
        info6 = info6[np.ix_(order, order)]
        upper = [info6[r, c] for r in range(6) for c in range(r, 6)]
        w, qx, qy, qz = rotation_to_quat(rel[:3, :3])
        nums = [*rel[:3, 3], qx, qy, qz, w, *upper]
        return f"EDGE_SE3:QUAT {va} {vb} " + " ".join(repr(float(v)) for v in nums)
