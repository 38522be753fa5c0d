"""SE(2) exponential, logarithm and adjoint on 4x4 planar poses (tangent order x, y, yaw).

A perturbation ``eps`` of a pose ``T`` is applied on the right (body frame): ``T @ exp(eps)``.
"""

from __future__ import annotations

import math

import numpy as np

from radarslam.geometry import se2_to_matrix


def _v_coeffs(theta: float) -> tuple[float, float]:
    """(a, b) of V(theta) = [[a, -b], [b, a]], the SE(2) exponential's translation part."""
    if abs(theta) < 1e-6:
        # Taylor expansion: sin(t)/t ~ 1 - t^2/6, (1 - cos t)/t ~ t/2.
        return 1.0 - theta * theta / 6.0, 0.5 * theta
    return math.sin(theta) / theta, (1.0 - math.cos(theta)) / theta


def exp_se2(xi) -> np.ndarray:
    """4x4 pose of the tangent vector ``(rho_x, rho_y, theta)`` (a constant twist times dt)."""
    rx, ry, theta = float(xi[0]), float(xi[1]), float(xi[2])
    a, b = _v_coeffs(theta)
    # V(theta) @ rho written out: the 2x2 matrix product cost more than the rest of the call
    return se2_to_matrix(a * rx - b * ry, b * rx + a * ry, theta)


def log_se2(pose: np.ndarray) -> np.ndarray:
    """Tangent vector ``(rho_x, rho_y, theta)`` of a 4x4 planar pose (z, roll, pitch ignored)."""
    theta = math.atan2(float(pose[1, 0]), float(pose[0, 0]))
    a, b = _v_coeffs(theta)
    # V(theta)^-1 = [[a, b], [-b, a]] / (a^2 + b^2), written out as exp_se2 writes V out
    x, y = float(pose[0, 3]), float(pose[1, 3])
    d = a * a + b * b
    return np.array([(a * x + b * y) / d, (a * y - b * x) / d, theta])


def adjoint_se2(pose: np.ndarray) -> np.ndarray:
    """3x3 adjoint: ``T exp(eps) = exp(Ad_T eps) T`` for body-frame tangent vectors."""
    c, s = pose[0, 0], pose[1, 0]
    n = np.hypot(c, s)
    c, s = c / n, s / n
    tx, ty = pose[0, 3], pose[1, 3]
    return np.array([[c, -s, ty], [s, c, -tx], [0.0, 0.0, 1.0]])


def planar(pose: np.ndarray) -> np.ndarray:
    """Project a 4x4 pose onto SE(2) (x, y, yaw; z = roll = pitch = 0), exactly orthonormal."""
    return se2_to_matrix(pose[0, 3], pose[1, 3], math.atan2(pose[1, 0], pose[0, 0]))


def exp_jacobian_twist(xi: np.ndarray) -> np.ndarray:
    """d log(exp(xi + d)) / d d at xi mapped to the body tangent of exp(xi): right Jacobian J_r.

    Used to propagate a twist covariance into the covariance of the integrated motion:
    ``Sigma_delta = J_r Sigma_xi J_r^T``.
    """
    x, y, th = float(xi[0]), float(xi[1]), float(xi[2])
    if abs(th) < 1e-6:
        return np.array([[1.0, th / 2, -y / 2], [-th / 2, 1.0, x / 2], [0.0, 0.0, 1.0]])
    s, c = np.sin(th), np.cos(th)
    a = s / th
    b = (1 - c) / th
    # Right Jacobian of SE(2) (Chirikjian; e.g. Sola et al. 2018, eq. 163).
    j13 = (th * x - y + y * c - x * s) / th**2
    j23 = (x + th * y - x * c - y * s) / th**2
    return np.array([[a, b, j13], [-b, a, j23], [0.0, 0.0, 1.0]])
