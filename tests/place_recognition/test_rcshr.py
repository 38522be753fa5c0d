import numpy as np
import pytest

from radarslam.errors import ConfigError
from radarslam.place_recognition.config import RerankConfig
from radarslam.place_recognition.rcshr import bin_edges, kl_divergence, rcs_histogram, rerank


def test_bin_edges_defaults_and_float_steps():
    e = bin_edges(0.02, 0.04)
    assert len(e) == 25 and e[0] == pytest.approx(0.02) and e[-1] == pytest.approx(0.98)
    # arange(0.04, 1.0, 0.04) would include ~1.0 by float error; the edges stay < 1
    assert bin_edges(0.04, 0.04)[-1] == pytest.approx(0.96)
    assert np.allclose(bin_edges(0.0, 0.25), [0.0, 0.25, 0.5, 0.75])
    with pytest.raises(ConfigError):
        bin_edges(0.9, 0.2)


def test_histogram_hand_example():
    edges = bin_edges(0.0, 0.25)  # bins [0, .25) [.25, .5) [.5, .75]; values above .75 ignored
    h = rcs_histogram(np.array([0.0, 0.1, 0.3, 0.75, 0.8, 1.0]), edges, epsilon=1e-5)
    counts = np.array([2, 1, 1]) + 1e-5
    np.testing.assert_allclose(h, counts / counts.sum())
    # default bins ignore the exact min 0 and max 1 of a min-max-normalised frame
    h = rcs_histogram(np.array([0.0, 0.03, 0.05, 0.51, 0.98, 1.0]), bin_edges(0.02, 0.04))
    raw = np.zeros(24)
    raw[[0, 12, 23]] = [2, 1, 1]
    np.testing.assert_allclose(h, (raw + 1e-5) / (raw + 1e-5).sum())


def test_kl_and_rerank_hand_example():
    q = np.array([0.5, 0.5])
    c = np.array([0.25, 0.75])
    assert kl_divergence(q, c) == pytest.approx(0.5 * np.log(2) + 0.5 * np.log(2 / 3))
    assert kl_divergence(q, q) == pytest.approx(0.0)
    # candidate 7 is nearer in descriptor space, candidate 3 has the same RCS histogram
    db_h = np.array([[0.5, 0.5]] * 10)
    db_h[7] = [0.01, 0.99]
    kl7 = kl_divergence(q, db_h[7])
    out = rerank(np.array([[7, 3]]), np.array([[0.5, 0.6]]), q[None], db_h, alpha=0.41)
    assert out.indices.tolist() == [[3, 7]]
    np.testing.assert_allclose(out.scores, [[0.59 * 0.6, 0.41 * kl7 + 0.59 * 0.5]])
    np.testing.assert_allclose(out.distances, [[0.6, 0.5]])
    # alpha 0 keeps the descriptor order
    assert rerank(np.array([[7, 3]]), np.array([[0.5, 0.6]]), q[None], db_h, 0.0).indices[0, 0] == 7
    assert RerankConfig().alpha == 0.41 and RerankConfig().top_m == 100
