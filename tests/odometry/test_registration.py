import numpy as np
import pytest

from radarslam.odometry.doppler import DopplerEstimator
from radarslam.odometry.lie import exp_se2, planar
from radarslam.odometry.registration import ScanToMapRegistration


def _reference_covariance(cloud, source, pose, max_dist, k, point_sigma):
    """The point-to-line Hessian written out with np.linalg (stacked eigh, explicit Jacobians)."""
    from scipy.spatial import cKDTree

    rot, t = pose[:2, :2], pose[:2, 3]
    pb = source[:, :2]
    pw = pb @ rot.T + t
    dist, idx = cKDTree(cloud).query(pw, k=k)
    ok = dist[:, 0] < max_dist
    nb = cloud[idx[ok]]
    centred = nb - nb.mean(axis=1, keepdims=True)
    scatter = np.einsum("mki,mkj->mij", centred, centred)
    vals, vecs = np.linalg.eigh(scatter)
    pw, pb = pw[ok], pb[ok]
    rows, res = [], []
    for i in range(len(pw)):
        jac = rot @ np.array([[1.0, 0.0, -pb[i, 1]], [0.0, 1.0, pb[i, 0]]])
        d = pw[i] - nb[i, 0]
        if vals[i, 1] > 4.0 * max(vals[i, 0], 1e-12):
            n = vecs[i, :, 0]
            rows.append(n @ jac)
            res.append(n @ d)
        else:
            rows.extend(jac)
            res.extend(d)
    jac, r = np.array(rows), np.array(res)
    var = max(np.mean(r**2), point_sigma**2)
    return np.linalg.inv(jac.T @ jac / var + np.eye(3) * 1e-6), int(ok.sum())


def _registration(
    cloud, max_num_iterations=50, refine=0, extrapolation=1.0, point_to_point="always"
):
    reg = ScanToMapRegistration(
        voxel_size_m=1.0,
        max_range_m=100.0,
        max_points_per_voxel=20,
        max_num_iterations=max_num_iterations,
        convergence_criterion=1e-4,
        fixed_sigma_m=0.7,
        point_sigma_m=0.1,
        line_neighbors=5,
        mirror_every=1,
        refine_iterations=refine,
        refine_max_extrapolation=extrapolation,
        point_to_point=point_to_point,
    )
    if len(cloud):
        reg.update(np.column_stack([cloud, np.zeros(len(cloud))]), np.eye(4))
    return reg


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_closed_form_covariance_matches_eigh_reference(seed):
    rng = np.random.default_rng(seed)
    # Two walls (lines) and a few compact reflector clusters (point-to-point rows).
    wall_a = np.column_stack([rng.uniform(-40, 40, 300), 8 + rng.normal(0, 0.05, 300)])
    wall_b = np.column_stack([25 + rng.normal(0, 0.05, 200), rng.uniform(-30, 30, 200)])
    poles = (rng.uniform(-30, 30, (15, 1, 2)) + rng.normal(0, 0.08, (15, 12, 2))).reshape(-1, 2)
    cloud = np.concatenate([wall_a, wall_b, poles])
    reg = _registration(cloud)
    mirror = reg.map.point_cloud()[:, :2]  # the map keeps what its voxels hold
    pose = exp_se2(np.array([0.4, -0.3, 0.02]))
    body = np.linalg.inv(pose)
    pick = rng.choice(len(mirror), 120, replace=False)
    world = mirror[pick] + rng.normal(0, 0.1, (120, 2))
    source = world @ body[:2, :2].T + body[:2, 3]
    source = np.column_stack([source, np.zeros(len(source))])
    cov, matched, _ = reg._covariance(source, pose, 3.0)
    ref, ref_matched = _reference_covariance(mirror, source, pose, 3.0, 5, 0.1)
    assert matched == ref_matched > 100
    np.testing.assert_allclose(cov, 0.5 * (ref + ref.T), rtol=1e-9, atol=1e-15)


def test_covariance_of_a_single_wall_is_unconstrained_along_it():
    rng = np.random.default_rng(3)
    wall = np.column_stack([rng.uniform(-50, 50, 600), 10 + rng.normal(0, 0.03, 600)])
    reg = _registration(wall)
    source = np.column_stack([rng.uniform(-40, 40, 80), np.full(80, 10.0), np.zeros(80)])
    cov, matched, _ = reg._covariance(source, np.eye(4), 3.0)
    assert matched == 80
    # Across the wall (y) a few cm; along it (x) orders of magnitude larger.
    assert np.sqrt(cov[1, 1]) < 0.05 and cov[0, 0] > 1e3 * cov[1, 1]


def test_observability_closed_form_matches_linalg():
    rng = np.random.default_rng(4)
    for lateral in (None, 0.1):
        est = DopplerEstimator()
        c = est.config
        for spread in (1e-3, 0.05, 0.5, 3.0):
            ang = rng.normal(0, spread, 40)
            a = np.column_stack([np.cos(ang), np.sin(ang), rng.normal(0, 1.0, 40) * spread])
            got = est._observability(a, lateral)
            eig = np.linalg.eigvalsh(a[:, :2].T @ a[:, :2] / len(a))[0]
            info = a.T @ a / c.noise_floor_mps**2
            if lateral is not None:
                info[1, 1] += 1.0 / lateral**2
            schur = info[2, 2] - info[2, :2] @ np.linalg.solve(info[:2, :2], info[:2, 2])
            assert got[0] == (eig > 1e-3)
            if got[0]:
                assert got[1] == (schur > 1.0 / 0.5**2)


def _radar_scan(reflectors, rng, azimuth_sigma_deg=0.4, range_sigma_m=0.15):
    """Reflectors seen with radar-like noise: the across-range error grows with the range."""
    rng_m = np.linalg.norm(reflectors, axis=1, keepdims=True)
    u = reflectors / rng_m
    perp = np.column_stack([-u[:, 1], u[:, 0]])
    across = rng_m * np.deg2rad(azimuth_sigma_deg) * rng.normal(0, 1, rng_m.shape)
    return reflectors + u * rng.normal(0, range_sigma_m, rng_m.shape) + perp * across


def test_refinement_pulls_yaw_into_noisy_reflector_clouds():
    """kiss-icp's nearest-point cost is nearly flat inside the clouds of noisy radar returns
    around each reflector: from a 1 deg yaw error it stops short (even with 100 iterations). The
    point-to-local-mean refinement (after 5 kiss-icp iterations) goes about half the rest, and
    on its own from the seed (the odometry's default: 8 steps, kiss-icp only as a fallback)
    as far."""
    errors = {"kiss-icp": [], "refined": [], "refinement alone": []}
    for seed in range(4):
        rng = np.random.default_rng(seed)
        refl = rng.uniform(-60, 60, (100, 2))
        refl = refl[np.linalg.norm(refl, axis=1) > 5]
        scans = [_radar_scan(refl, rng) for _ in range(16)]
        guess = exp_se2(np.array([0.1, -0.1, np.deg2rad(1.0)]))
        for name, iterations, refine, point_to_point in (
            ("kiss-icp", 100, 0, "always"),
            ("refined", 5, 5, "always"),
            ("refinement alone", 5, 8, "fallback"),
        ):
            reg = _registration(np.zeros((0, 2)), iterations, refine, point_to_point=point_to_point)
            for pts in scans[:-1]:  # the map: 15 noisy scans of the same reflectors
                reg.update(np.column_stack([pts, np.zeros(len(pts))]), np.eye(4))
            source, _ = reg.voxelize(np.column_stack([scans[-1], np.zeros(len(refl))]))
            pose = reg.align(source, guess).world_from_ego
            errors[name].append(abs(np.rad2deg(np.arctan2(pose[1, 0], pose[0, 0]))))
    kiss, refined = np.mean(errors["kiss-icp"]), np.mean(errors["refined"])
    assert refined < 0.08 and refined < 0.6 * kiss, errors
    assert np.mean(errors["refinement alone"]) < 0.08, errors


def test_extrapolated_refinement_gets_nearer_the_fixed_point_per_search():
    """The local mean follows the point, so plain Gauss-Newton steps shrink geometrically; with
    Aitken's extrapolation the same number of correspondence searches gets nearer the fixed
    point (the refinement run for 60 plain steps)."""
    gaps: dict[str, list[float]] = {}
    for seed in range(4):
        rng = np.random.default_rng(10 + seed)
        refl = rng.uniform(-60, 60, (100, 2))
        refl = refl[np.linalg.norm(refl, axis=1) > 5]
        scans = [_radar_scan(refl, rng) for _ in range(16)]
        guess = exp_se2(np.array([0.3, -0.2, np.deg2rad(0.8)]))
        poses = {}
        for refine, extrapolation in ((60, 1.0), (3, 1.0), (5, 1.0), (3, 8.0), (5, 8.0)):
            reg = _registration(np.zeros((0, 2)), 1, refine, extrapolation)
            for pts in scans[:-1]:
                reg.update(np.column_stack([pts, np.zeros(len(pts))]), np.eye(4))
            source, _ = reg.voxelize(np.column_stack([scans[-1], np.zeros(len(refl))]))
            poses[(refine, extrapolation)] = reg.align(source, guess).world_from_ego
        ref = poses.pop((60, 1.0))
        for key, pose in poses.items():
            d = np.linalg.inv(ref) @ pose
            gap = np.hypot(d[0, 3], d[1, 3]) + 10 * abs(np.arctan2(d[1, 0], d[0, 0]))
            gaps.setdefault(f"{key[0]} x{key[1]:g}", []).append(gap)
    mean = {k: float(np.mean(v)) for k, v in gaps.items()}
    assert mean["3 x8"] < 0.75 * mean["3 x1"], mean
    assert mean["5 x8"] < 0.85 * mean["5 x1"], mean


def test_refinement_ignores_points_at_the_edge_of_the_map():
    """Points whose nearest map points do not all lie within the correspondence distance sit at
    the edge of the map, where the few neighbours they have lie behind them (the side the
    vehicle came from): they leave the refinement alone."""
    rng = np.random.default_rng(3)
    refl = rng.uniform(-40, 40, (80, 2))
    refl = refl[np.linalg.norm(refl, axis=1) > 5]
    reg = _registration(np.zeros((0, 2)), refine=3, extrapolation=8.0)
    for _ in range(10):
        pts = _radar_scan(refl, rng)
        reg.update(np.column_stack([pts, np.zeros(len(pts))]), np.eye(4))
    # The edge: two map points behind a cluster of new returns 0.6-1.0 m further ahead.
    edge_map = np.array([[60.0, 0.0], [60.0, 0.4]])
    reg.update(np.column_stack([edge_map, np.zeros(2)]), np.eye(4))
    edge_scan = np.column_stack([rng.uniform(60.6, 61.0, 12), rng.uniform(-0.2, 0.6, 12)])
    scan = np.column_stack([_radar_scan(refl, rng), np.zeros(len(refl))])
    with_edge = np.concatenate([scan, np.column_stack([edge_scan, np.zeros(12)])])
    start = exp_se2(np.array([0.02, -0.01, np.deg2rad(0.05)]))
    inside, stepped = reg._refine(scan, start, 2.1, 0.7)
    both, _ = reg._refine(with_edge, start, 2.1, 0.7)
    assert stepped
    np.testing.assert_array_equal(both, inside)


@pytest.mark.parametrize("refine, point_to_point", [(3, "always"), (8, "fallback")])
def test_yaw_search_finds_a_scan_turned_beyond_the_registrations_reach(refine, point_to_point):
    # Scattered reflectors (posts, corners) around the vehicle; the scan is the map seen from a
    # pose 9 deg and 0.3 m off the seed, as after an outage whose held yaw rate overturned.
    rng = np.random.default_rng(7)
    cloud = rng.uniform(-60, 60, (400, 2))
    cloud = cloud[np.hypot(*cloud.T) > 4.0]
    truth = exp_se2(np.array([0.3, -0.2, np.deg2rad(9.0)]))
    scan = (cloud - truth[:2, 3]) @ truth[:2, :2]  # ego-frame points of the truth
    scan = scan[np.hypot(*scan.T) < 50.0]
    scan = scan + rng.normal(0, 0.05, scan.shape)
    source = np.column_stack([scan, np.zeros(len(scan))])
    reg = _registration(cloud, 5, refine, 8.0, point_to_point)

    def yaw_deg(result):
        return float(
            np.degrees(np.arctan2(result.world_from_ego[1, 0], result.world_from_ego[0, 0]))
        )

    plain = reg.align(source, np.eye(4))
    searched = reg.align_over_yaw(source, np.eye(4), np.deg2rad(15.0), np.deg2rad(1.5))
    assert abs(yaw_deg(searched) - 9.0) < 0.3
    np.testing.assert_allclose(searched.world_from_ego[:2, 3], [0.3, -0.2], atol=0.1)
    assert searched.num_matched > plain.num_matched
    assert abs(yaw_deg(plain) - 9.0) > 2.0  # the plain alignment stays near its seed
    # A search of zero width is the plain alignment.
    same = reg.align_over_yaw(source, np.eye(4), 0.0, np.deg2rad(1.5))
    np.testing.assert_array_equal(same.world_from_ego, plain.world_from_ego)


def test_load_kernels_compiles_what_the_registration_runs():
    """In a fresh process, after load_kernels() an alignment with its refinement and
    covariance adds no kernel signature: the first frame finds everything loaded."""
    import subprocess
    import sys

    code = """
import numpy as np
from radarslam import grid_kernels
from radarslam.odometry import registration_kernels as rk
from radarslam.odometry.registration import ScanToMapRegistration, load_kernels
kernels = (grid_kernels.bounds, grid_kernels.build, grid_kernels.query, rk.refine_pose,
           rk.covariance_sums)
load_kernels()
before = [len(k.signatures) for k in kernels]
reg = ScanToMapRegistration(voxel_size_m=1.0, max_range_m=100.0, max_points_per_voxel=20,
    max_num_iterations=5, convergence_criterion=1e-4, fixed_sigma_m=0.7, point_sigma_m=0.3,
    line_neighbors=5, mirror_every=5, refine_iterations=8, refine_max_extrapolation=8.0,
    point_to_point="fallback")
pts = np.random.default_rng(0).uniform(-30, 30, (300, 3)); pts[:, 2] = 0
reg.update(pts, np.eye(4))
reg.align(reg.voxelize(pts)[0], np.eye(4))
after = [len(k.signatures) for k in kernels]
assert all(before) and before == after, (before, after)
"""
    subprocess.run([sys.executable, "-c", code], check=True, timeout=300)


def _reflector_map(rng):
    """Reflectors scattered around the origin, and a fallback registration (8 refinement steps)
    whose map holds 15 noisy radar scans of them seen from the origin."""
    refl = rng.uniform(-60, 60, (100, 2))
    refl = refl[np.hypot(*refl.T) > 5]
    reg = _registration(np.zeros((0, 2)), 5, 8, 8.0, "fallback")
    for _ in range(15):
        pts = _radar_scan(refl, rng)
        reg.update(np.column_stack([pts, np.zeros(len(pts))]), np.eye(4))
    return refl, reg


def test_fallback_runs_kiss_icp_only_where_the_refinement_cannot_start():
    """``point_to_point="fallback"``: against a map of single scattered points no scan point
    has five map neighbours within reach, so kiss-icp aligns the scan (as "always" does);
    against clouds of radar returns the refinement alone aligns it, and kiss-icp's alignment is
    not called."""
    rng = np.random.default_rng(5)
    posts = rng.uniform(-50, 50, (300, 2))
    posts = posts[np.hypot(*posts.T) > 4.0]
    truth = exp_se2(np.array([0.4, -0.3, np.deg2rad(0.5)]))
    scan = (posts - truth[:2, 3]) @ truth[:2, :2]
    source = np.column_stack([scan, np.zeros(len(scan))])
    sparse = {mode: _registration(posts, 5, 8, 8.0, mode) for mode in ("always", "fallback")}
    poses = {mode: reg.align(source, np.eye(4)).world_from_ego for mode, reg in sparse.items()}
    np.testing.assert_array_equal(poses["fallback"], poses["always"])
    np.testing.assert_allclose(poses["fallback"][:2, 3], truth[:2, 3], atol=0.02)

    class NoKiss:
        def align_points_to_map(self, **kwargs):
            raise AssertionError("kiss-icp's alignment ran")

    refl, reg = _reflector_map(rng)
    reg.registration = NoKiss()
    guess = exp_se2(np.array([0.1, -0.1, np.deg2rad(0.5)]))
    pose = reg.align(np.column_stack([_radar_scan(refl, rng), np.zeros(len(refl))]), guess)
    assert abs(np.degrees(np.arctan2(pose.world_from_ego[1, 0], pose.world_from_ego[0, 0]))) < 0.1
    np.testing.assert_allclose(pose.world_from_ego[:2, 3], 0.0, atol=0.05)


def _refine_in_numpy(reg, source, pose, max_dist, sigma):
    """The refinement's steps written with numpy (what registration_kernels.refine_pose runs)."""
    from radarslam.odometry.linalg3 import solve3
    from radarslam.odometry.registration import _STEP_METRIC
    from radarslam.odometry.registration_kernels import refine_sums

    tree, cloud = reg._mirror_tree()
    pb = np.ascontiguousarray(source[:, :2])
    previous = None
    for _ in range(reg.refine_iterations):
        rot, t = pose[:2, :2], pose[:2, 3]
        pw = pb @ rot.T + t
        dist, idx = tree.query(pw, reg.line_neighbors, max_dist)
        used, sw, hxt, hyt, htt, gx, gy, gt = refine_sums(
            pb, pw, dist, idx, cloud, max_dist, sigma**2, np.ascontiguousarray(rot)
        )
        if used < 3:
            return pose, previous is not None
        hess = np.array([[sw, 0.0, hxt], [0.0, sw, hyt], [hxt, hyt, htt]])
        delta = -solve3(hess + np.eye(3) * 1e-9, np.array([gx, gy, gt]))
        scale = 1.0
        if previous is not None:
            rho = float(previous * _STEP_METRIC @ delta) / float(previous * _STEP_METRIC @ previous)
            if 0.0 < rho < 1.0:
                scale = min(1.0 / (1.0 - rho), reg.refine_max_extrapolation)
        pose = planar(pose @ exp_se2(scale * delta))
        previous = delta
        if np.abs(delta).max() < 1e-4:
            break
    return pose, True


def test_compiled_refinement_takes_the_documented_steps():
    for seed in range(8):
        rng = np.random.default_rng(seed)
        refl, reg = _reflector_map(rng)
        source = np.column_stack([_radar_scan(refl, rng), np.zeros(len(refl))])
        seed_pose = exp_se2(np.array([*rng.normal(0, 0.2, 2), np.deg2rad(rng.normal(0, 1))]))
        got, stepped = reg._refine(source, seed_pose, 2.1, 0.7)
        want, want_stepped = _refine_in_numpy(reg, source, seed_pose, 2.1, 0.7)
        assert stepped == want_stepped
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-9)
    # No step (a map too sparse for any complete neighbourhood): the pose comes back as is.
    reg = _registration(np.array([[0.0, 0.0], [30.0, 0.0]] * 3), 5, 8, 8.0, "fallback")
    pose, stepped = reg._refine(source, seed_pose, 2.1, 0.7)
    assert not stepped and pose is seed_pose
