"""Inverse and solve of 3x3 matrices in closed form.

The odometry inverts and solves a dozen 3x3 systems per frame (twist covariances, the fusion's
gain, Gauss-Newton steps). ``np.linalg`` spends about 20 us of dispatch and type checks on each,
several times the arithmetic; the cofactor formulas on Python floats below take a few us.
Singular or non-finite input goes to ``np.linalg``, which raises its ``LinAlgError`` as before.
"""

from __future__ import annotations

import math

import numpy as np


def _cofactors(m: np.ndarray):
    (a, b, c), (d, e, f), (g, h, i) = m.tolist()
    # adjugate (transposed cofactor matrix), row by row
    c00, c01, c02 = e * i - f * h, c * h - b * i, b * f - c * e
    c10, c11, c12 = f * g - d * i, a * i - c * g, c * d - a * f
    c20, c21, c22 = d * h - e * g, b * g - a * h, a * e - b * d
    det = a * c00 + b * c10 + c * c20
    return (c00, c01, c02, c10, c11, c12, c20, c21, c22), det


def inv3(m: np.ndarray) -> np.ndarray:
    """``np.linalg.inv`` of one (3, 3) matrix."""
    adj, det = _cofactors(m)
    if det == 0.0 or not math.isfinite(det):
        return np.linalg.inv(m)
    s = 1.0 / det
    return np.array([c * s for c in adj]).reshape(3, 3)


def solve3(m: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``np.linalg.solve`` of one (3, 3) system with a (3,) right-hand side."""
    adj, det = _cofactors(m)
    if det == 0.0 or not math.isfinite(det):
        return np.linalg.solve(m, v)
    x, y, z = v.tolist()
    s = 1.0 / det
    return np.array(
        [
            (adj[0] * x + adj[1] * y + adj[2] * z) * s,
            (adj[3] * x + adj[4] * y + adj[5] * z) * s,
            (adj[6] * x + adj[7] * y + adj[8] * z) * s,
        ]
    )
