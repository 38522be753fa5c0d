import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from radarslam import neighbors
from radarslam.errors import ConfigError
from radarslam.neighbors import GridIndex


def _radar_like_map(seed: int, n: int = 6000, reflectors: int = 300, extent_m: float = 100.0):
    """Clouds of returns around reflectors, as kiss-icp's map of radar scans looks."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-extent_m, extent_m, (reflectors, 2))
    return centres[rng.integers(0, reflectors, n)] + rng.normal(0.0, 0.4, (n, 2)), rng


def _tree_query(cloud, q, k, bound=math.inf):
    dist, idx = cKDTree(cloud).query(q, k=k, distance_upper_bound=bound)
    if k == 1:
        dist, idx = dist[:, None], idx[:, None]
    return dist, idx


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize(
    ("k", "bound", "cell_m"),
    [
        (5, 2.1, 1.0),
        (1, 0.5, 1.0),
        (5, math.inf, 1.0),
        (7, 10.0, 1.0),
        (3, 2.1, 0.3),
        (5, 2.1, 7.0),
    ],
)
def test_matches_ckdtree_exactly(seed, k, bound, cell_m):
    cloud, rng = _radar_like_map(seed)
    q = cloud[rng.integers(0, len(cloud), 400)] + rng.normal(0.0, 1.5, (400, 2))
    # queries far outside the map's bounding box, on its corner and in an empty stretch
    q = np.vstack([q, [[500.0, 500.0], [-300.0, 20.0], [0.0, 0.0], cloud.min(axis=0)]])
    dist, idx = GridIndex(cloud, cell_m=cell_m).query(q, k, bound)
    ref_dist, ref_idx = _tree_query(cloud, q, k, bound)
    np.testing.assert_array_equal(dist, ref_dist)
    np.testing.assert_array_equal(idx, ref_idx)
    if math.isfinite(bound):  # some rows must be partial, or the bound was never exercised
        assert np.isinf(dist[:, -1]).any() and np.isfinite(dist[:, 0]).any()


def test_nearest_within_gives_up_only_on_far_queries():
    cloud, rng = _radar_like_map(3)
    q = rng.uniform(-110.0, 110.0, (500, 2))
    dist, idx = GridIndex(cloud).query(q, 5, nearest_within=2.1)
    ref_dist, ref_idx = _tree_query(cloud, q, 5)
    near = ref_dist[:, 0] < 2.1
    assert 50 < near.sum() < 450
    np.testing.assert_array_equal(dist[near], ref_dist[near])  # unbounded, exact
    np.testing.assert_array_equal(idx[near], ref_idx[near])
    assert np.isinf(dist[~near]).all() and (idx[~near] == len(cloud)).all()


def test_fewer_points_than_k_and_empty_index():
    cloud = np.array([[0.0, 0.0], [1.0, 0.0], [5.0, 5.0]])
    dist, idx = GridIndex(cloud).query(np.array([[0.2, 0.0]]), 5)
    np.testing.assert_allclose(dist[0, :3], [0.2, 0.8, math.hypot(4.8, 5.0)])
    assert idx[0].tolist() == [0, 1, 2, 3, 3] and np.isinf(dist[0, 3:]).all()
    empty = GridIndex(np.zeros((0, 2)))
    dist, idx = empty.query(np.array([[0.0, 0.0], [1.0, 1.0]]), 2, 3.0)
    assert dist.shape == (2, 2) and np.isinf(dist).all() and (idx == 0).all()


def test_duplicate_points_keep_index_order():
    cloud = np.array([[1.0, 1.0], [3.0, 3.0], [1.0, 1.0], [1.0, 1.0]])
    dist, idx = GridIndex(cloud).query(np.array([[1.0, 1.0]]), 3)
    assert idx[0].tolist() == [0, 2, 3] and (dist == 0.0).all()


def test_huge_extent_coarsens_the_grid(monkeypatch):
    monkeypatch.setattr(neighbors, "_MAX_CELLS", 1000)
    cloud, rng = _radar_like_map(4, n=2000, extent_m=1000.0)
    grid = GridIndex(cloud, cell_m=1.0)
    assert grid.nx * grid.ny <= 1000 and grid.cell_m > 1.0
    q = rng.uniform(-1000.0, 1000.0, (200, 2))
    dist, idx = grid.query(q, 4, 50.0)
    ref_dist, ref_idx = _tree_query(cloud, q, 4, 50.0)
    np.testing.assert_array_equal(dist, ref_dist)
    np.testing.assert_array_equal(idx, ref_idx)


def test_non_finite_query_rows_come_back_empty():
    cloud, _ = _radar_like_map(5, n=500)
    q = np.array([[np.nan, 0.0], [0.0, np.inf], [cloud[0, 0], cloud[0, 1]]])
    dist, idx = GridIndex(cloud).query(q, 2)
    assert np.isinf(dist[:2]).all() and (idx[:2] == len(cloud)).all()
    assert idx[2, 0] == 0 and dist[2, 0] == 0.0


def test_bad_inputs_are_one_line_errors():
    with pytest.raises(ConfigError, match="cell_m"):
        GridIndex(np.zeros((3, 2)), cell_m=0.0)
    with pytest.raises(ValueError, match=r"\(n, 2\) points"):
        GridIndex(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="NaN or inf"):
        GridIndex(np.array([[0.0, 0.0], [np.nan, 1.0]]))
    grid = GridIndex(np.zeros((3, 2)))
    with pytest.raises(ValueError, match=r"\(m, 2\) points"):
        grid.query(np.zeros(2), 1)
    with pytest.raises(ValueError, match="k must be >= 1"):
        grid.query(np.zeros((1, 2)), 0)


@pytest.mark.parametrize(("radius", "cell_m"), [(0.5, 0.5), (2.0, 1.0), (0.5, 3.0)])
def test_count_within_matches_brute_force(radius, cell_m):
    cloud, rng = _radar_like_map(6, n=3000, reflectors=150, extent_m=30.0)
    q = np.vstack([cloud[:500], rng.uniform(-40.0, 40.0, (300, 2)), [[1e4, -1e4]]])
    dist = np.hypot(q[:, None, 0] - cloud[None, :, 0], q[:, None, 1] - cloud[None, :, 1])
    full = (dist <= radius).sum(axis=1)
    grid = GridIndex(cloud, cell_m=cell_m)
    for stop_at in (1, 3, 10**6):
        np.testing.assert_array_equal(
            grid.count_within(q, radius, stop_at), np.minimum(full, stop_at)
        )
    assert full.max() > 3 and (full == 0).any()  # both ends were exercised
    with pytest.raises(ValueError, match="radius_m"):
        grid.count_within(q, -1.0, 3)
    assert (GridIndex(np.zeros((0, 2))).count_within(q, radius, 3) == 0).all()
