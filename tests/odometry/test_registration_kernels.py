import numpy as np
from scipy.spatial import cKDTree

from radarslam.odometry.lie import exp_se2
from radarslam.odometry.registration_kernels import covariance_sums, refine_sums


def _scene(seed):
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-40.0, 40.0, (120, 2))
    cloud = centres[rng.integers(0, 120, 3000)] + rng.normal(0.0, 0.4, (3000, 2))
    pb = centres[rng.integers(0, 120, 250)] + rng.normal(0.0, 0.6, (250, 2))
    pb = np.vstack([pb, rng.uniform(60.0, 90.0, (20, 2))])  # beyond the map: no neighbour
    pose = exp_se2(np.array([0.3, -0.2, 0.02]))
    rot = np.ascontiguousarray(pose[:2, :2])
    return cloud, pb, rot, pb @ rot.T + pose[:2, 3]


def test_refine_sums_match_the_numpy_formulas():
    cloud, pb, rot, pw = _scene(0)
    max_dist, s2, k = 2.1, 0.49, 5
    dist, idx = cKDTree(cloud).query(pw, k=k, distance_upper_bound=max_dist)
    valid = dist < max_dist
    ok = valid[:, -1]
    nb = cloud[np.where(valid, idx, 0)[ok]]
    mean = (nb * valid[ok][..., None]).sum(axis=1) / valid[ok].sum(axis=1)[:, None]
    r = pw[ok] - mean
    rb = r @ rot
    w = (s2 / (s2 + (r**2).sum(axis=1))) ** 2
    qx, qy = -pb[ok, 1], pb[ok, 0]
    expected = [w.sum(), w @ qx, w @ qy, w @ (qx**2 + qy**2)]
    expected += [w @ rb[:, 0], w @ rb[:, 1], w @ (qx * rb[:, 0] + qy * rb[:, 1])]
    used, *sums = refine_sums(pb, pw, dist, idx, cloud, max_dist, s2, rot)
    assert used == ok.sum() and 20 < used < len(pb)  # incomplete neighbourhoods were exercised
    np.testing.assert_allclose(sums, expected, rtol=1e-12, atol=1e-9)


def test_covariance_sums_split_lines_from_blobs():
    cloud, pb, rot, pw = _scene(1)
    # a straight wall: its points' neighbourhoods are lines
    wall = np.column_stack([np.linspace(-30.0, 30.0, 400), np.full(400, 45.0)])
    cloud = np.vstack([cloud, wall])
    t = np.array([0.3, -0.2])
    pb = np.vstack([pb, (wall[::20] + np.array([0.0, 0.1]) - t) @ rot])
    pw = pb @ rot.T + t
    dist, idx = cKDTree(cloud).query(pw, k=5)
    matched, hess, sq, n_res = covariance_sums(pb, pw, dist, idx, cloud, 2.1, rot)
    assert matched == int((dist[:, 0] < 2.1).sum())
    assert matched < n_res < 2 * matched  # some point-to-line rows, some point-to-point pairs
    np.testing.assert_array_equal(hess, hess.T)
    assert np.all(np.linalg.eigvalsh(hess) > 0) and sq > 0
