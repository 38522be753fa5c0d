import numpy as np
import pytest

from radarslam.errors import DataError
from radarslam.place_recognition.metrics import pr_curve, recall_at_n, save_pr_plot


def test_recall_at_n_hand_example():
    correct = np.array(
        [
            [True, False, False, False],
            [False, False, True, False],
            [False, False, False, False],
            [False, True, True, False],
        ]
    )
    r = recall_at_n(correct, [1, 2, 3, 10])
    assert r == {1: 0.25, 2: 0.5, 3: 0.75, 10: 0.75}
    with pytest.raises(DataError):
        recall_at_n(np.zeros((0, 3), bool), [1])


def test_pr_curve_reference_definitions():
    scores = np.array([0.10, 0.20, 0.30, 0.40])
    correct = np.array([True, False, True, False])
    c = pr_curve(scores, correct, decimals=2)
    # th 0.1 accepts nothing (strict <): skipped; 0.2 -> P 1, R 0.5; 0.3 -> 0.5, 0.5; 0.4 -> 2/3, 1
    np.testing.assert_allclose(c.thresholds, [0.2, 0.3, 0.4])
    np.testing.assert_allclose(c.precision, [1.0, 0.5, 2 / 3])
    np.testing.assert_allclose(c.recall, [0.5, 0.5, 1.0])
    assert c.max_f1 == pytest.approx(0.8)
    # left Riemann sum over points sorted by recall (stable): 1*0 + 0.5*0.5
    assert c.average_precision == pytest.approx(0.25)


def test_pr_curve_rounding_groups_scores():
    scores = np.array([0.101, 0.104, 0.2049, 0.31])
    correct = np.array([True, True, False, True])
    c = pr_curve(scores, correct, decimals=2)
    # unique rounded thresholds 0.1, 0.2, 0.31: at 0.1 nothing is accepted (0.101 >= 0.1)
    np.testing.assert_allclose(c.thresholds, [0.2, 0.31])
    np.testing.assert_allclose(c.precision, [1.0, 2 / 3])
    np.testing.assert_allclose(c.recall, [2 / 3, 2 / 3])


def test_pr_plot_written(tmp_path):
    c = pr_curve(np.array([0.1, 0.2, 0.3, 0.4]), np.array([True, False, True, False]))
    p = save_pr_plot({"a": c}, tmp_path / "pr.png", title="t")
    assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list(tmp_path.glob(".*tmp*"))
