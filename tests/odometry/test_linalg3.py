"""The closed-form 3x3 inverse and solve against np.linalg."""

import numpy as np
import pytest

from radarslam.odometry.linalg3 import inv3, solve3


def _matrices(seed: int, n: int):
    rng = np.random.default_rng(seed)
    for _ in range(n):
        a = rng.normal(size=(3, 3))
        # covariances and information matrices from 1e-8 to 1e6 per axis, as the odometry's
        yield a @ a.T + np.diag(10.0 ** rng.uniform(-8, 6, 3)), rng.normal(size=3)


def test_inverse_and_solve_match_linalg():
    worst_inv = worst_solve = 0.0
    for m, v in _matrices(0, 2000):
        ref = np.linalg.inv(m)
        worst_inv = max(worst_inv, np.abs(inv3(m) - ref).max() / np.abs(ref).max())
        ref_x = np.linalg.solve(m, v)
        worst_solve = max(worst_solve, np.abs(solve3(m, v) - ref_x).max() / np.abs(ref_x).max())
    assert worst_inv < 1e-9
    assert worst_solve < 1e-9


def test_general_matrix():
    m = np.array([[0.0, 2.0, 1.0], [1.0, 0.0, 3.0], [4.0, -1.0, 0.5]])  # needs pivoting in LU
    np.testing.assert_allclose(inv3(m) @ m, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(m @ solve3(m, np.array([1.0, 2.0, 3.0])), [1.0, 2.0, 3.0])


def test_singular_raises_as_linalg():
    singular = np.array([[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 1.0, 1.0]])
    with pytest.raises(np.linalg.LinAlgError):
        inv3(singular)
    with pytest.raises(np.linalg.LinAlgError):
        solve3(singular, np.ones(3))


def test_non_finite_input_as_linalg():
    bad = np.eye(3)
    bad[0, 1] = np.inf
    np.testing.assert_array_equal(inv3(bad), np.linalg.inv(bad))  # NaN where np.linalg has NaN
    np.testing.assert_array_equal(solve3(bad, np.ones(3)), np.linalg.solve(bad, np.ones(3)))
