"""Ego routes (canonical loops shared by logs, driven in both directions) and TUM trajectories."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from radarslam.errors import DataError
from radarslam.io.text import read_text
from radarslam.sim.traffic import EgoMotion, random_walk
from radarslam.sim.world import StreetNetwork


def canonical_routes(
    net: StreetNetwork, rng: np.random.Generator, n_routes: int, length_m: float
) -> list[list[int]]:
    """Routes that several logs share (revisits); they start near the city centre."""
    centre = net.nodes.mean(0)
    dist = np.linalg.norm(net.nodes - centre, axis=1)
    central = np.argsort(dist)[: max(4, len(dist) // 4)]
    routes = []
    for _ in range(n_routes):
        a = int(rng.choice(central))
        b = int(rng.choice(net.neighbours(a)))
        routes.append(random_walk(net, rng, (a, b), length_m))
    return routes


def extend_route(net: StreetNetwork, rng: np.random.Generator, seq: list[int], length_m: float):
    """``seq`` continued by a random walk until it covers ``length_m``."""
    pts = net.nodes[seq]
    have = float(np.linalg.norm(np.diff(pts, axis=0), axis=1).sum())
    if have >= length_m:
        return list(seq)
    tail = random_walk(net, rng, (seq[-2], seq[-1]), length_m - have)
    return list(seq) + tail[2:]


#: The fastest ego motion a TUM trajectory to drive along may have (m/s, 360 km/h).
MAX_TUM_SPEED_MPS = 100.0


def read_tum(path: str | Path) -> np.ndarray:
    """(N, 8) rows timestamp_s x y z qx qy qz qw, sorted by time, timestamps strictly increasing."""
    path = Path(path)
    text = read_text(path, "TUM trajectory file")
    rows = []
    lines = []
    for no, line in enumerate(text.splitlines(), 1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise DataError(
                f"{path}:{no}: expected 8 values (t x y z qx qy qz qw), got {len(parts)}"
            )
        try:
            rows.append([float(x) for x in parts])
            lines.append(no)
        except ValueError:
            raise DataError(f"{path}:{no}: non-numeric value in {line!r}") from None
    if len(rows) < 4:
        raise DataError(f"{path}: a TUM trajectory needs at least 4 poses, got {len(rows)}")
    arr = np.array(rows)
    if not np.all(np.isfinite(arr)):
        raise DataError(f"{path}: contains non-finite values")
    if np.any(np.diff(arr[:, 0]) <= 0):
        i = int(np.flatnonzero(np.diff(arr[:, 0]) <= 0)[0]) + 1
        raise DataError(
            f"{path}:{lines[i]}: timestamp {float(arr[i, 0])!r} is not later than the previous "
            "one; timestamps must be strictly increasing"
        )
    # A jump (a corrupt line, coordinates in other units) would make the simulated city follow
    # it: a street of one point per metre, gigabytes for a jump of a million kilometres.
    dt = np.diff(arr[:, 0])
    dist = np.hypot(*np.diff(arr[:, 1:3], axis=0).T)
    speed = dist / dt
    if np.any(speed > MAX_TUM_SPEED_MPS):
        i = int(np.argmax(speed > MAX_TUM_SPEED_MPS)) + 1
        raise DataError(
            f"{path}:{lines[i]}: pose is {dist[i - 1]:.6g} m from the previous one "
            f"{dt[i - 1]:.6g} s earlier ({speed[i - 1]:.3g} m/s; a vehicle drives at most "
            f"{MAX_TUM_SPEED_MPS:g} m/s): wrong units, or a corrupt line?"
        )
    qn = np.linalg.norm(arr[:, 4:8], axis=1)
    if np.any(qn < 1e-6):
        raise DataError(f"{path}: contains a zero quaternion")
    return arr


class TumEgo:
    """Ego motion interpolated from a TUM trajectory with C2 cubic splines (x, y, unwrapped yaw).

    Velocities are the spline derivatives, so poses and the Doppler sensor velocity agree exactly.
    Time 0 of the drive is the first TUM timestamp.
    """

    def __init__(self, tum: np.ndarray):
        from scipy.interpolate import CubicSpline

        t = tum[:, 0] - tum[0, 0]
        qx, qy, qz, qw = tum[:, 4], tum[:, 5], tum[:, 6], tum[:, 7]
        yaw = np.unwrap(np.arctan2(2 * (qw * qz + qx * qy), 1 - 2 * (qy * qy + qz * qz)))
        self.duration_s = float(t[-1])
        self.t0_abs = float(tum[0, 0])
        self._x = CubicSpline(t, tum[:, 1])
        self._y = CubicSpline(t, tum[:, 2])
        self._yaw = CubicSpline(t, yaw)
        self.xy = tum[:, 1:3]

    def ego(self, t) -> EgoMotion:
        t = np.clip(np.asarray(t, dtype=np.float64), 0.0, self.duration_s)
        xy = np.column_stack([self._x(t), self._y(t)])
        yaw = self._yaw(t)
        vw = np.column_stack([self._x(t, 1), self._y(t, 1)])
        c, s = np.cos(yaw), np.sin(yaw)
        v_fwd = c * vw[:, 0] + s * vw[:, 1]
        v_lat = -s * vw[:, 0] + c * vw[:, 1]
        return EgoMotion(xy, yaw, v_fwd, v_lat, self._yaw(t, 1))
