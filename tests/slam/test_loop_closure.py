import numpy as np
import pytest

from radarslam.errors import DataError
from radarslam.geometry import invert, matrix_to_se2, se2_to_matrix
from radarslam.io.loops import NodeKey
from radarslam.neighbors import GridIndex
from radarslam.slam.loop_closure import LoopVerifier, LoopVerifierConfig, persistent_points
from radarslam.slam.synthetic_graph import observe_place, random_place


def _revisit(seed, q_from_place):
    place = random_place(seed, points_per_m=3)
    query = observe_place(place, q_from_place, seed=1000 + seed, dropout=0.3, noise_m=0.15)
    cand = observe_place(place, np.eye(4), seed=2000 + seed, dropout=0.3, noise_m=0.15)
    return query, cand, invert(q_from_place)  # candidate_from_query (candidate frame = place)


def _pose_error(est, true):
    err = matrix_to_se2(invert(true) @ est)
    return float(np.hypot(err[0], err[1])), float(np.degrees(abs(err[2])))


@pytest.fixture(scope="module")
def verifier():
    return LoopVerifier()


@pytest.mark.parametrize(
    "q_from_place",
    [
        se2_to_matrix(4.0, -3.0, np.deg2rad(12.0)),  # same direction, shifted
        se2_to_matrix(-6.0, 5.0, np.deg2rad(183.0)),  # revisited in the opposite direction
        se2_to_matrix(7.0, 2.0, np.deg2rad(-97.0)),  # crossing at a right angle
    ],
)
def test_true_revisit_is_accepted_with_the_right_pose(verifier, q_from_place):
    query, cand, true = _revisit(3, q_from_place)
    v = verifier.verify(query, cand, None)
    assert v.accepted, v.reason
    assert v.reason == "ok"
    t_err, r_err = _pose_error(v.candidate_from_query, true)
    assert t_err < 0.15 and r_err < 0.5
    assert v.fitness > 0.8 and v.inlier_rmse_m < 0.4 and v.overlap > 0.6
    info = v.information
    assert np.allclose(info, info.T) and np.all(np.linalg.eigvalsh(info) > 0)
    cov = np.linalg.inv(info)
    # floor keeps the loop from claiming better than 0.1 m / 0.5 deg
    assert np.sqrt(cov[0, 0]) >= 0.1 and np.sqrt(cov[2, 2]) >= np.deg2rad(0.5)


def test_wrong_place_is_rejected_with_reason(verifier):
    query, _, _ = _revisit(3, se2_to_matrix(4.0, -3.0, 0.2))
    other = observe_place(random_place(77, points_per_m=3), np.eye(4), seed=5)
    v = verifier.verify(query, other, None)
    assert not v.accepted
    assert "fitness" in v.reason and v.fitness < 0.5


def test_rejects_a_series_of_wrong_places_and_accepts_revisits(verifier):
    accepted_wrong = 0
    accepted_true = 0
    for seed in range(8):
        rng = np.random.default_rng(seed)
        q_from_place = se2_to_matrix(*rng.uniform(-8, 8, 2), rng.uniform(-np.pi, np.pi))
        query, cand, true = _revisit(10 + seed, q_from_place)
        v = verifier.verify(query, cand)
        accepted_true += v.accepted and _pose_error(v.candidate_from_query, true)[0] < 0.3
        wrong = observe_place(random_place(900 + seed, points_per_m=3), np.eye(4), seed=seed)
        accepted_wrong += verifier.verify(query, wrong).accepted
    assert accepted_true == 8 and accepted_wrong == 0


def test_initial_guess_suffices_without_search():
    q_from_place = se2_to_matrix(20.0, -15.0, np.deg2rad(140.0))  # beyond the search radius
    query, cand, true = _revisit(4, q_from_place)
    guess = true @ se2_to_matrix(0.8, -0.5, np.deg2rad(4.0))
    v = LoopVerifier(LoopVerifierConfig(correlative_search=False, heading_step_deg=360))
    res = v.verify(query, cand, guess)
    assert res.accepted and _pose_error(res.candidate_from_query, true)[0] < 0.15


@pytest.mark.parametrize(
    ("q_yaw_deg", "found"),
    [(183.0, True), (205.0, True), (97.0, False), (0.0, False)],
)
def test_heading_window_tries_only_headings_near_the_hint(q_yaw_deg, found):
    # A turned-image candidate: a half turn is the hint, +-30 deg the window (3 hypotheses).
    q_from_place = se2_to_matrix(-6.0, 5.0, np.deg2rad(q_yaw_deg))
    query, cand, true = _revisit(3, q_from_place)
    v = LoopVerifier(LoopVerifierConfig(heading_range_deg=60.0))
    every = LoopVerifier(LoopVerifierConfig(heading_range_deg=60.0, refine_top_k=10))
    hyps = every.hypotheses(query, cand, np.eye(4))
    assert sorted(h.heading_deg for h in hyps) == [-30.0, 0.0, 30.0]
    res = v.verify(query, cand, se2_to_matrix(0.0, 0.0, np.pi))
    assert (res.accepted and _pose_error(res.candidate_from_query, true)[0] < 0.15) == found
    assert LoopVerifier().verify(query, cand).accepted  # all round, every case is found


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_grid_icp_is_open3d_icp(seed):
    """The default backend replays open3d's point-to-point iterations: the same poses to 1e-9."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-60.0, 60.0, (250, 2))
    cand = centres[rng.integers(0, 250, 2500)] + rng.normal(0.0, 0.3, (2500, 2))
    yaw = rng.normal(0.0, 0.1)
    rot = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    query = (cand[rng.integers(0, 2500, 1200)] + rng.normal(0.0, 0.3, (1200, 2))) @ rot
    query = np.vstack([query - rng.normal(0.0, 1.5, 2), rng.uniform(-60.0, 60.0, (200, 2))])
    open3d = LoopVerifier(LoopVerifierConfig(backend="open3d"))
    grid = LoopVerifier(LoopVerifierConfig(backend="grid"))
    index = GridIndex(cand)
    for max_corr in (3.0, 1.0, 0.2):
        ref = open3d.icp_open3d(query, cand, np.eye(4), max_corr)
        got = index.icp_point_to_point(query, np.eye(4), max_corr, 1e-4, 1e-4, 30)
        np.testing.assert_allclose(got[:2, [0, 1, 3]], ref[:2, [0, 1, 3]], atol=1e-9)
    # both stages, as verification runs them
    np.testing.assert_allclose(
        grid.icp(query, cand, np.eye(4)), open3d.icp(query, cand, np.eye(4)), atol=1e-9
    )
    # the whole verification: the same decision, pose and scores
    query, cand, true = _revisit(5, se2_to_matrix(-2.0, 3.0, np.deg2rad(178.0)))
    va, vb = open3d.verify(query, cand), grid.verify(query, cand)
    assert va.accepted and vb.accepted and _pose_error(vb.candidate_from_query, true)[0] < 0.15
    np.testing.assert_allclose(vb.candidate_from_query, va.candidate_from_query, atol=1e-9)
    assert abs(va.fitness - vb.fitness) < 1e-12 and abs(va.tight_fitness - vb.tight_fitness) < 1e-12


def test_too_few_points_and_bad_input(verifier):
    v = verifier.verify(np.zeros((5, 2)), np.random.default_rng(0).normal(size=(500, 2)) * 10)
    assert not v.accepted and "too few points" in v.reason
    with pytest.raises(DataError, match="query cloud must be"):
        verifier.verify(np.zeros(10), np.zeros((10, 2)))
    with pytest.raises(DataError, match="initial guess"):
        verifier.verify(np.zeros((50, 2)), np.zeros((50, 2)), np.eye(3))


def test_verify_candidate_logs_every_outcome():
    v = LoopVerifier()
    query, cand, _ = _revisit(6, se2_to_matrix(1.0, 1.0, 0.1))
    rec, _ver = v.verify_candidate(
        NodeKey("a", 40), NodeKey("a", 2), 4_000_000, 200_000, 0.3, query, cand
    )
    v.verify_candidate(
        NodeKey("a", 41),
        NodeKey("b", 9),
        4_100_000,
        90_000,
        0.7,
        query,
        observe_place(random_place(99), np.eye(4), seed=1),
    )
    assert [r.accepted for r in v.log] == [True, False]
    assert rec.reason == "ok" and rec.candidate == NodeKey("a", 2)
    assert v.log[1].reason != "ok"


def test_tight_fitness_rejects_a_blurred_match():
    # The same place seen with 0.6 m noise aligns within 1 m (fitness passes) but hardly any
    # point lands within 0.3 m: the tight test is what rejects such vague matches.
    q_from_place = se2_to_matrix(3.0, 1.0, 0.3)
    place = random_place(8, points_per_m=3)
    cand = observe_place(place, np.eye(4), seed=1, dropout=0.3, noise_m=0.15)
    sharp = observe_place(place, q_from_place, seed=2, dropout=0.3, noise_m=0.15)
    vague = observe_place(place, q_from_place, seed=2, dropout=0.3, noise_m=0.6)
    guess = invert(q_from_place)
    loose = LoopVerifier(LoopVerifierConfig(min_tight_fitness=0.0, max_inlier_rmse_m=1.0))
    strict = LoopVerifier(LoopVerifierConfig(min_tight_fitness=0.3, max_inlier_rmse_m=1.0))
    assert strict.verify(sharp, cand, guess).accepted
    v = strict.verify(vague, cand, guess)
    assert not v.accepted and v.reason.startswith("tight_fitness")
    assert loose.verify(vague, cand, guess).accepted
    assert v.tight_fitness < strict.verify(sharp, cand, guess).tight_fitness


def test_max_range_crops_far_points_before_registration():
    q_from_place = se2_to_matrix(2.0, -1.0, 0.1)
    query, cand, true = _revisit(9, q_from_place)
    far = np.array([[150.0, 0.0], [0.0, -180.0]])
    cropped = LoopVerifier(LoopVerifierConfig(max_range_m=60.0, correlative_search=False))
    res = cropped.verify(np.vstack([query, far]), np.vstack([cand, far * 1.1]), true)
    assert res.accepted and _pose_error(res.candidate_from_query, true)[0] < 0.15
    # every point beyond the range gone: too few left when only far points remain
    assert "too few points" in cropped.verify(far.repeat(50, 0), cand, true).reason


def _corridor(seed, q_from_street, length_m=120.0):
    """Two straight kerb lines 12 m apart with parked-car clutter seen from two poses: nothing
    but the lines' cross direction is constrained."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-length_m / 2, length_m / 2, size=(2, int(length_m * 2)))
    street = np.column_stack(
        [np.r_[x[0], x[1]], np.r_[np.full(x.shape[1], 6.0), np.full(x.shape[1], -6.0)]]
    )
    query = observe_place(street, q_from_street, seed=seed + 1, clutter_fraction=0.0)
    cand = observe_place(street, np.eye(4), seed=seed + 2, clutter_fraction=0.0)
    return query, cand


def test_constraint_ratio_flags_a_street_that_only_constrains_its_cross_direction():
    loose = LoopVerifier(LoopVerifierConfig(correlative_search=False, heading_step_deg=360))
    query, cand = _corridor(1, se2_to_matrix(-3.0, 0.5, 0.02))
    true = invert(se2_to_matrix(-3.0, 0.5, 0.02))
    # started 3 m along the street from the truth, ICP stays there with a fit as good as the truth's
    slid = loose.verify(query, cand, true @ se2_to_matrix(3, 0, 0))
    assert slid.accepted and _pose_error(slid.candidate_from_query, true)[0] > 2.0
    assert slid.constraint_ratio < 0.1
    place_query, place_cand, place_true = _revisit(3, se2_to_matrix(4.0, -3.0, 0.2))
    assert loose.verify(place_query, place_cand, place_true).constraint_ratio > 0.5
    strict = LoopVerifier(
        LoopVerifierConfig(correlative_search=False, heading_step_deg=360, min_constraint_ratio=0.5)
    )
    v = strict.verify(query, cand, true)
    assert not v.accepted and v.reason.startswith("constraint_ratio")
    assert strict.verify(place_query, place_cand, place_true).accepted


def test_persistent_points_keeps_points_with_enough_neighbours():
    xy = np.array([[0.0, 0.0], [0.3, 0.0], [0.0, 0.4], [5.0, 5.0], [5.4, 5.0]])
    np.testing.assert_array_equal(persistent_points(xy, 2, 0.5), xy[:3])  # itself not counted
    np.testing.assert_array_equal(persistent_points(xy, 1, 0.5), xy)
    assert persistent_points(xy, 0, 0.5) is xy
    assert len(persistent_points(np.zeros((0, 2)), 2, 0.5)) == 0
    assert len(persistent_points(xy[:2], 2, 0.5)) == 0
    rng = np.random.default_rng(0)
    cloud = rng.uniform(0, 20, (3000, 2))
    counts = np.array([np.sum(np.hypot(*(cloud - p).T) <= 0.5) - 1 for p in cloud])
    np.testing.assert_array_equal(persistent_points(cloud, 3, 0.5), cloud[counts >= 3])
    # Dense reflector clusters (decided by their grid cell alone) among sparse returns, some
    # pairs exactly a radius apart: the same points as counting every distance.
    centres = rng.uniform(0, 30, (200, 2))
    clusters = centres[rng.integers(0, 200, 4000)] + rng.normal(0, 0.2, (4000, 2))
    pairs = rng.uniform(0, 30, (100, 2))
    partners = pairs + np.array([0.5, 0.0])
    cloud = np.vstack([clusters, rng.uniform(0, 30, (1500, 2)), pairs, partners])
    d2 = ((cloud[:, None, :] - cloud[None, :, :]) ** 2).sum(axis=-1)
    for k in (1, 2, 5):
        counts = (d2 <= 0.25).sum(axis=1) - 1
        np.testing.assert_array_equal(persistent_points(cloud, k, 0.5), cloud[counts >= k])


def _drive(seed, lane_y, heading):
    """What one drive down a street (facades at y = +-9 m) sees, in the frame of its pose at
    x = 0: each facade scatterer returns five noisy detections; static-looking clutter, one
    detection each, lies at random within 15 m of the drive's path."""
    rng = np.random.default_rng(seed)
    facade = np.array([(x, y) for x in np.arange(-40.0, 40.0, 1.5) for y in (-9.0, 9.0)])
    facade = facade[rng.uniform(size=len(facade)) < 0.7]
    walls = np.repeat(facade, 5, axis=0) + rng.normal(0, 0.1, (5 * len(facade), 2))
    along = rng.uniform(-25, 25, 150)
    r, a = 15 * np.sqrt(rng.uniform(size=150)), rng.uniform(0, 2 * np.pi, 150)
    clutter = np.column_stack([along + r * np.cos(a), lane_y + r * np.sin(a)])
    pose = se2_to_matrix(0.0, lane_y, heading)
    to_ego = invert(pose)
    points = np.vstack([walls, clutter])
    return points @ to_ego[:2, :2].T + to_ego[:2, 3], pose


def test_persistence_filter_keeps_path_clutter_out_of_a_reversed_registration():
    # A street driven the other way in the other lane: each map's clutter follows its own path,
    # and matching it pulls the registration off; repeated facade returns survive the filter.
    errors = {0: [], 2: []}
    for seed in range(6):
        cand, world_from_cand = _drive(seed, -1.75, 0.0)
        query, world_from_query = _drive(100 + seed, 1.75, np.pi)
        true = invert(world_from_cand) @ world_from_query
        for min_neighbors in errors:
            cfg = LoopVerifierConfig(
                correlative_search=False, heading_step_deg=360, min_neighbors=min_neighbors
            )
            res = LoopVerifier(cfg).verify(query, cand, true @ se2_to_matrix(0.3, -0.3, 0.01))
            assert res.accepted
            errors[min_neighbors].append(_pose_error(res.candidate_from_query, true)[0])
    assert max(errors[2]) < 0.05
    assert max(errors[0]) > 0.2


def test_cached_maps_give_the_same_verification():
    cand, world_from_cand = _drive(7, -1.75, 0.0)
    query, world_from_query = _drive(107, 1.75, np.pi)
    guess = invert(world_from_cand) @ world_from_query @ se2_to_matrix(0.3, -0.3, 0.01)
    cfg = LoopVerifierConfig(correlative_search=False, heading_step_deg=360, min_neighbors=2)
    plain = LoopVerifier(cfg).verify(query, cand, guess)
    cached = LoopVerifier(cfg)
    keys = ("query", "candidate")
    first = cached.verify(query, cand, guess, cache_keys=keys)
    # A key names the map's content: the second call takes the prepared maps from the cache.
    again = cached.verify(query[:0], cand[:0], guess, cache_keys=keys)
    for res in (first, again):
        assert res.accepted == plain.accepted and res.fitness == plain.fitness
        np.testing.assert_array_equal(res.candidate_from_query, plain.candidate_from_query)
    # Bounded: the oldest keys are dropped.
    for n in range(LoopVerifier.cache_size + 5):
        cached.verify(query, cand, guess, cache_keys=(("q", n), ("c", n)))
    assert cached.cached_maps == LoopVerifier.cache_size
    rejected = cached.verify(query[:0], cand[:0], guess, cache_keys=keys)
    assert not rejected.accepted and rejected.reason.startswith("too few points")


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_translation_search_matches_brute_force(seed):
    # The FFT search spans only the grid under the queries: every shift's score must still be
    # the plain sum, including queries hanging over the grid's edge, and ties go to the
    # smallest shift.
    from radarslam.slam.loop_closure import _LikelihoodGrid

    rng = np.random.default_rng(seed)
    cand = rng.uniform(0.0, 60.0, size=(400, 2))
    queries = [
        rng.uniform(-20.0, 40.0, size=(150, 2)),
        cand[:120] + rng.normal(0.0, 0.3, size=(120, 2)) + [6.0, -4.0],
        rng.uniform(50.0, 90.0, size=(80, 2)),  # mostly beyond the grid
    ]
    grid = _LikelihoodGrid(cand, cell_m=2.0)
    radius_m, r = 9.0, 5
    found = grid.best_shifts(queries, radius_m)
    for q, (shift, score) in zip(queries, found, strict=True):
        cells = np.unique(np.floor((q - grid.origin) / grid.cell).astype(int), axis=0)
        best, best_d2, scores = -1.0, None, {}
        for sx in range(-r, r + 1):
            for sy in range(-r, r + 1):
                idx = cells + np.array([sx, sy])
                inside = np.all((idx >= 0) & (idx < grid.grid.shape), axis=1)
                s = float(grid.grid[idx[inside, 0], idx[inside, 1]].sum())
                scores[sx, sy] = s
                d2 = sx * sx + sy * sy
                if s > best + 1e-9 or (abs(s - best) < 1e-9 and d2 < best_d2):
                    best, best_d2 = s, d2
        i, j = np.round(shift / grid.cell).astype(int)
        assert scores[i, j] == pytest.approx(best)
        assert i * i + j * j == best_d2
        assert score == pytest.approx(best / len(cells))
    assert found[1][0] == pytest.approx([-6.0, 4.0])  # undoes the (6, -4) m offset
