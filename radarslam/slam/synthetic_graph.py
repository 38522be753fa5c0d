"""Seeded synthetic pose-graph problems (multi-lap circuits with noisy odometry, true and false
loop closures) for the back-end tests and ``bench/backend.py``, ``bench/slam.py``. Pure numpy,
except :func:`grow_isam2`, which drives the GTSAM back end."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from radarslam.geometry import invert, se2_to_matrix


@dataclass(frozen=True)
class SyntheticLoop:
    i: int  # earlier node (the "candidate")
    j: int  # later node (the "query")
    i_from_j: np.ndarray  # 4x4 measurement
    true: bool  # False for injected outliers


@dataclass(frozen=True)
class SyntheticGraph:
    gt: np.ndarray  # (N, 4, 4) world_from_ego ground truth
    odometry: np.ndarray  # (N-1, 4, 4) noisy ego_i_from_ego_{i+1}
    odometry_covariance: np.ndarray  # 3x3 (x, y, yaw)
    loops: list[SyntheticLoop] = field(default_factory=list)
    loop_information: np.ndarray = field(default_factory=lambda: np.eye(3))

    @property
    def dead_reckoning(self) -> np.ndarray:
        """(N, 4, 4) odometry chained from the true first pose."""
        out = [self.gt[0]]
        for rel in self.odometry:
            out.append(out[-1] @ rel)
        return np.stack(out)


def _noise_pose(rng, sigmas) -> np.ndarray:
    dx, dy, dth = rng.normal(scale=sigmas)
    return se2_to_matrix(dx, dy, dth)


def multilap_circuit(
    num_laps: int = 3,
    poses_per_lap: int = 100,
    radius_m: float = 40.0,
    odometry_sigmas: tuple[float, float, float] = (0.05, 0.05, 0.004),
    loop_every: int = 5,
    loop_sigmas: tuple[float, float, float] = (0.1, 0.1, 0.01),
    false_loop_fraction: float = 0.0,
    seed: int = 0,
) -> SyntheticGraph:
    """A circle driven ``num_laps`` times; every ``loop_every``-th node of laps >= 1 gets a true
    loop to the same place one lap earlier (measured with ``loop_sigmas`` noise). Then
    ``false_loop_fraction`` x (number of true loops) outliers are added between random nodes at
    least a quarter lap apart, with a measurement that is plausible-looking (a few metres, random
    heading) but wrong."""
    rng = np.random.default_rng(seed)
    n = num_laps * poses_per_lap
    th = 2 * np.pi * np.arange(n) / poses_per_lap
    gt = np.stack([se2_to_matrix(radius_m * np.sin(a), radius_m * (1 - np.cos(a)), a) for a in th])
    odo_sig = np.asarray(odometry_sigmas, dtype=np.float64)
    odometry = np.stack(
        [invert(gt[k]) @ gt[k + 1] @ _noise_pose(rng, odo_sig) for k in range(n - 1)]
    )
    loops: list[SyntheticLoop] = []
    loop_sig = np.asarray(loop_sigmas, dtype=np.float64)
    for j in range(poses_per_lap, n, loop_every):
        i = j - poses_per_lap
        meas = invert(gt[i]) @ gt[j] @ _noise_pose(rng, loop_sig)
        loops.append(SyntheticLoop(i, j, meas, True))
    num_false = round(false_loop_fraction * len(loops))
    for _ in range(num_false):
        while True:
            j = int(rng.integers(poses_per_lap // 4, n))
            i = int(rng.integers(0, j - poses_per_lap // 4 + 1))
            # a wrong place: genuinely far from where i sees j
            if np.linalg.norm(gt[i][:2, 3] - gt[j][:2, 3]) > 10.0:
                break
        dx, dy = rng.uniform(-3, 3, size=2)
        meas = se2_to_matrix(dx, dy, rng.uniform(-np.pi, np.pi))
        loops.append(SyntheticLoop(i, j, meas, False))
    loops.sort(key=lambda lp: lp.j)
    return SyntheticGraph(
        gt=gt,
        odometry=odometry,
        odometry_covariance=np.diag(odo_sig**2),
        loops=loops,
        loop_information=np.diag(1.0 / loop_sig**2),
    )


def random_place(
    seed: int,
    extent_m: float = 60.0,
    num_walls: int = 8,
    num_poles: int = 25,
    points_per_m: float = 1.5,
) -> np.ndarray:
    """Noise-free structure of a place: points along random wall segments plus poles, (K, 2)."""
    rng = np.random.default_rng(seed)
    pts = []
    for _ in range(num_walls):
        a = rng.uniform(-extent_m / 2, extent_m / 2, size=2)
        ang = rng.uniform(0, np.pi)
        length = rng.uniform(8, 30)
        b = a + length * np.array([np.cos(ang), np.sin(ang)])
        s = rng.uniform(0, 1, size=int(length * points_per_m))
        pts.append(a + s[:, None] * (b - a))
    pts.append(rng.uniform(-extent_m / 2, extent_m / 2, size=(num_poles, 2)))
    return np.concatenate(pts)


def observe_place(
    structure_xy: np.ndarray,
    view_from_place: np.ndarray,
    seed: int,
    noise_m: float = 0.15,
    dropout: float = 0.3,
    clutter_fraction: float = 0.1,
    extent_m: float = 60.0,
) -> np.ndarray:
    """A radar-like local map of a place seen from another pose: the structure resampled with
    point dropout, Gaussian noise and uniform clutter, expressed in the ``view`` frame (N, 2)."""
    rng = np.random.default_rng(seed)
    keep = rng.uniform(size=len(structure_xy)) >= dropout
    pts = structure_xy[keep] + rng.normal(scale=noise_m, size=(int(keep.sum()), 2))
    clutter = rng.uniform(-extent_m / 2, extent_m / 2, size=(int(clutter_fraction * len(pts)), 2))
    pts = np.concatenate([pts, clutter])
    view = np.asarray(view_from_place, dtype=np.float64)
    return pts @ view[:2, :2].T + view[:2, 3]


@dataclass
class Isam2Growth:
    """iSAM2 fed one key frame at a time over a synthetic multi-lap graph (:func:`grow_isam2`)."""

    graph: object  # the PoseGraph, holding the grown estimate
    synthetic: SyntheticGraph
    num_nodes: int
    loops_at: dict[int, list[SyntheticLoop]]  # later node -> the loops closed there
    update_ms: np.ndarray  # (num_nodes - 1,) iSAM2 update time per added key frame
    with_loop: np.ndarray  # (num_nodes - 1,) bool: that key frame closed a loop
    total_s: float

    @property
    def num_loops(self) -> int:
        return sum(len(v) for v in self.loops_at.values())


def grow_isam2(
    num_nodes: int = 10_000,
    poses_per_lap: int = 500,
    loop_every: int = 25,
    robust: str = "cauchy",
    false_loop_fraction: float = 0.0,
    seed: int = 0,
    progress: bool = False,
) -> Isam2Growth:
    """The back end's per-key-frame cost as a graph grows to ``num_nodes``: each step adds one
    odometry factor and the loops closing at that node, then runs one iSAM2 update (what the SLAM
    pipeline does per key frame, on a graph of any size)."""
    import time

    from radarslam.io.loops import NodeKey
    from radarslam.slam.pose_graph import PoseGraph, PoseGraphConfig

    laps = int(np.ceil(num_nodes / poses_per_lap))
    sg = multilap_circuit(
        num_laps=laps,
        poses_per_lap=poses_per_lap,
        radius_m=80.0,
        loop_every=loop_every,
        false_loop_fraction=false_loop_fraction,
        seed=seed,
    )
    n = min(num_nodes, len(sg.gt))
    loops_at: dict[int, list[SyntheticLoop]] = {}
    for lp in sg.loops:
        if lp.j < n:
            loops_at.setdefault(lp.j, []).append(lp)
    pg = PoseGraph(PoseGraphConfig(loop_robust=robust))
    pg.add_session("s", sg.gt[0], anchor="prior")
    pg.update()
    steps = range(n - 1)
    if progress:
        from tqdm import tqdm

        steps = tqdm(steps, desc="iSAM2", unit="kf", mininterval=1.0)
    update_ms, with_loop = [], []
    t0 = time.perf_counter()
    for k in steps:
        pg.add_odometry("s", k, k + 1, sg.odometry[k], sg.odometry_covariance)
        for lp in loops_at.get(k + 1, []):
            pg.add_loop(NodeKey("s", lp.i), NodeKey("s", lp.j), lp.i_from_j, sg.loop_information)
        update_ms.append(pg.update() * 1e3)
        with_loop.append(k + 1 in loops_at)
    return Isam2Growth(
        pg, sg, n, loops_at, np.asarray(update_ms), np.asarray(with_loop, dtype=bool),
        time.perf_counter() - t0,
    )  # fmt: skip
