"""Place-recognition metrics with the AutoPlace reference code's definitions.

- recall@N: a query is correct when any of its top-N database frames lies within the positive
  radius; the denominator is every query.
- PR curve: top-1 match verification. Thresholds are the unique top-1 scores rounded to
  ``decimals`` (ascending); a query is accepted when its top-1 score is strictly below the
  threshold; TP/FP/FN/TN from acceptance x top-1 correctness; thresholds whose precision or recall
  denominator is zero are skipped.
- max F1 over the PR points; AP = left Riemann sum sum_j P_j (R_{j+1} - R_j) over the points sorted
  by recall (no interpolation, nothing below the smallest recall).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from radarslam.errors import DataError


def recall_at_n(correct: np.ndarray, ns: Sequence[int]) -> dict[int, float]:
    """``correct`` (Q, K) bool: whether the k-th retrieved frame is a true match."""
    correct = np.asarray(correct, dtype=bool)
    if correct.ndim != 2:
        raise DataError(f"correct must be (Q, K), got shape {correct.shape}")
    if correct.shape[0] == 0:
        raise DataError("no queries to evaluate")
    cum = np.logical_or.accumulate(correct, axis=1) if correct.shape[1] else correct
    out = {}
    for n in ns:
        col = min(n, correct.shape[1]) - 1
        out[int(n)] = float(cum[:, col].mean()) if col >= 0 else 0.0
    return out


@dataclass(frozen=True)
class PRCurve:
    thresholds: np.ndarray
    precision: np.ndarray
    recall: np.ndarray

    @property
    def max_f1(self) -> float:
        p, r = self.precision, self.recall
        s = p + r
        ok = s > 0
        if not ok.any():
            return 0.0
        return float(np.max(2 * p[ok] * r[ok] / s[ok]))

    @property
    def average_precision(self) -> float:
        if len(self.recall) < 2:
            return 0.0
        order = np.argsort(self.recall, kind="stable")
        r, p = self.recall[order], self.precision[order]
        return float(np.sum(p[:-1] * np.diff(r)))


def pr_curve(top1_scores: np.ndarray, top1_correct: np.ndarray, decimals: int = 2) -> PRCurve:
    """Top-1 match-verification PR curve (lower score = more confident)."""
    s = np.asarray(top1_scores, dtype=np.float64)
    c = np.asarray(top1_correct, dtype=bool)
    if s.shape != c.shape or s.ndim != 1:
        raise DataError(f"scores {s.shape} and correctness {c.shape} must be equal 1-D arrays")
    if not np.all(np.isfinite(s)):
        raise DataError("top-1 scores contain NaN or infinity")
    thresholds = np.unique(np.round(s, decimals))
    acc = s[None, :] < thresholds[:, None]  # (T, Q)
    tp = np.sum(acc & c, axis=1)
    fp = np.sum(acc & ~c, axis=1)
    fn = np.sum(~acc & c, axis=1)
    ok = (tp + fp > 0) & (tp + fn > 0)
    prec = tp[ok] / (tp[ok] + fp[ok])
    rec = tp[ok] / (tp[ok] + fn[ok])
    return PRCurve(
        thresholds=thresholds[ok], precision=prec.astype(float), recall=rec.astype(float)
    )


def save_pr_plot(curves: dict[str, PRCurve], path: str | Path, title: str = "") -> Path:
    """PNG of one or more PR curves, written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from radarslam.io.atomic import atomic_path

    path = Path(path)
    fig, ax = plt.subplots(figsize=(5, 4.5), dpi=120)
    for name, curve in curves.items():
        order = np.argsort(curve.recall, kind="stable")
        label = f"{name} (maxF1 {curve.max_f1:.3f}, AP {curve.average_precision:.3f})"
        ax.plot(curve.recall[order], curve.precision[order], label=label, lw=1.5)
    ax.set_xlabel("recall")
    ax.set_ylabel("precision")
    ax.set_xlim(0, 1.02)
    ax.set_ylim(0, 1.02)
    ax.grid(alpha=0.3)
    if title:
        ax.set_title(title)
    ax.legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)
    return path
