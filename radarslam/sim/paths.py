"""Smooth 2-D driving paths along the street network: straight lane lines joined by circular arcs.

A path is parametrised by arc length; many paths are concatenated into one :class:`PathSet`
(path k's arc length ``s`` is the global coordinate ``offset[k] + s``) so that the poses of all
agents are evaluated in a handful of vectorised numpy calls.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from radarslam.sim.world import StreetNetwork


def fillet(delta: float, radius: float, n_ramp: int = 6) -> tuple[float, list[tuple[float, float]]]:
    """Tangent length and (length, curvature) pieces of a turn by ``delta`` with radius ``radius``.

    The curvature ramps up and down in ``n_ramp`` steps (a staircase clothoid) so that the yaw
    rate of a vehicle following the path changes in small steps instead of one jump.
    """
    sgn = 1.0 if delta >= 0 else -1.0
    ad = abs(delta)
    k_max = 1.0 / radius
    ramp_len = min(8.0, 0.4 * radius * ad)
    ramp = [((j / (n_ramp + 1)) * k_max, ramp_len / n_ramp) for j in range(1, n_ramp + 1)]
    turned = 2 * sum(k * ln for k, ln in ramp)
    main = max(ad - turned, 0.0) / k_max
    pieces = [(ln, sgn * k) for k, ln in ramp] + [(main, sgn * k_max)]
    pieces += [(ln, sgn * k) for k, ln in reversed(ramp)]
    x = y = th = 0.0
    for ln, k in pieces:
        if ln <= 0:
            continue
        x += (np.sin(th + k * ln) - np.sin(th)) / k
        y += -(np.cos(th + k * ln) - np.cos(th)) / k
        th += k * ln
    t2 = y / np.sin(th) if abs(np.sin(th)) > 1e-9 else 0.0
    t1 = x - t2 * np.cos(th)
    return float(t1), [(ln, k) for ln, k in pieces if ln > 1e-9]


@dataclass
class PathSpec:
    """Pieces of one path (local arc length)."""

    s0: np.ndarray
    length: np.ndarray
    xy0: np.ndarray
    th0: np.ndarray
    kappa: np.ndarray
    edge_key: np.ndarray  # directed edge (a * n_nodes + b) each piece belongs to
    along0: np.ndarray  # position along that edge at the piece start (for car following)
    stop_s: np.ndarray  # stop lines before signalised nodes
    stop_node: np.ndarray
    stop_group: np.ndarray  # 0: approach along x, 1: along y (signal groups)
    total: float


def build_path(
    net: StreetNetwork,
    seq: list[int],
    offset_m: float,
    r_right_m: float,
    r_left_m: float,
    stop_back_m: float,
    start_along_m: float = 0.0,
) -> PathSpec:
    """Lane path through the node sequence ``seq`` (right-hand traffic, lane ``offset_m`` right)."""
    nodes = net.nodes
    n_nodes = len(nodes)
    k = len(seq) - 1
    if k < 1:
        raise ValueError("a path needs at least two nodes")
    a = nodes[seq[:-1]]
    b = nodes[seq[1:]]
    d = b - a
    ln = np.linalg.norm(d, axis=1)
    d = d / ln[:, None]
    right = np.column_stack([d[:, 1], -d[:, 0]])
    la = a + right * offset_m  # lane line start / end
    lb = b + right * offset_m
    th = np.arctan2(d[:, 1], d[:, 0])
    # Corner i joins lane i and lane i + 1.
    delta = (th[1:] - th[:-1] + np.pi) % (2 * np.pi) - np.pi
    radius = np.where(delta < 0, r_right_m, r_left_m)
    # Nearly straight through an intersection: a long gentle arc, not a turn-radius one.
    gentle = np.abs(delta) < np.deg2rad(35.0)
    radius = np.where(
        gentle, np.maximum(radius, 12.0 / np.tan(np.maximum(np.abs(delta), 1e-6) / 2)), radius
    )
    corner = np.zeros((max(k - 1, 0), 2))
    for i in range(k - 1):
        den = d[i, 0] * d[i + 1, 1] - d[i, 1] * d[i + 1, 0]
        if abs(den) < 1e-6:
            corner[i] = (lb[i] + la[i + 1]) / 2
            continue
        w = la[i + 1] - la[i]
        t = (w[0] * d[i + 1, 1] - w[1] * d[i + 1, 0]) / den
        corner[i] = la[i] + t * d[i]
    # Line i runs from the previous corner (or la[0]) to corner i (or lb[-1]).
    starts = np.vstack([la[:1] + d[:1] * start_along_m, corner])
    ends = np.vstack([corner, lb[-1:]])
    seg_len = np.einsum("ij,ij->i", ends - starts, d)
    # Fillets (composite turns), shrunk until they fit in both neighbouring lines.
    tang = np.zeros(max(k - 1, 0))
    turns: list[list[tuple[float, float]]] = []
    for i in range(k - 1):
        if abs(delta[i]) < 1e-4:
            turns.append([])
            continue
        lim = 0.45 * min(seg_len[i], seg_len[i + 1])
        rad = float(radius[i])
        for _ in range(8):
            t, pcs = fillet(float(delta[i]), rad)
            if t <= lim:
                break
            rad *= max(lim / t, 0.1) * 0.98
        tang[i] = t
        turns.append(pcs)
    t_in = np.concatenate([[0.0], tang])  # trimmed at the start of line i
    t_out = np.concatenate([tang, [0.0]])
    s0, lens, xy0, th0, kap, ekey, al0 = [], [], [], [], [], [], []
    stop_s, stop_node, stop_group = [], [], []
    s = 0.0
    for i in range(k):
        p0 = starts[i] + d[i] * t_in[i]
        line_len = max(seg_len[i] - t_in[i] - t_out[i], 0.0)
        key = seq[i] * n_nodes + seq[i + 1]
        along_start = float(np.dot(p0 - la[i], d[i]))
        s0.append(s)
        lens.append(line_len)
        xy0.append(p0)
        th0.append(th[i])
        kap.append(0.0)
        ekey.append(key)
        al0.append(along_start)
        if i < k - 1 and net.has_light[seq[i + 1]]:
            dist_to_node = float(np.dot(b[i] - p0, d[i]))
            s_stop = s + min(max(dist_to_node - stop_back_m, 0.0), line_len)
            stop_s.append(s_stop)
            stop_node.append(seq[i + 1])
            stop_group.append(0 if abs(d[i, 0]) >= abs(d[i, 1]) else 1)
        s += line_len
        if i < k - 1 and turns[i]:
            next_key = seq[i + 1] * n_nodes + seq[i + 2]
            xy = p0 + d[i] * line_len
            heading = float(th[i])
            along = -float(tang[i]) - float(np.dot(la[i + 1] - corner[i], d[i + 1]))
            for ln, kap_ in turns[i]:
                s0.append(s)
                lens.append(ln)
                xy0.append(xy.copy())
                th0.append(heading)
                kap.append(kap_)
                ekey.append(next_key)
                al0.append(along)
                xy = xy + np.array(
                    [
                        (np.sin(heading + kap_ * ln) - np.sin(heading)) / kap_,
                        -(np.cos(heading + kap_ * ln) - np.cos(heading)) / kap_,
                    ]
                )
                heading += kap_ * ln
                along += ln
                s += ln
    return PathSpec(
        np.array(s0),
        np.array(lens),
        np.array(xy0),
        np.array(th0),
        np.array(kap),
        np.array(ekey, np.int64),
        np.array(al0),
        np.array(stop_s),
        np.array(stop_node, np.int64),
        np.array(stop_group, np.int64),
        s,
    )


@dataclass
class PathSet:
    s0: np.ndarray  # global piece start
    xy0: np.ndarray
    th0: np.ndarray
    kappa: np.ndarray
    edge_key: np.ndarray
    along0: np.ndarray
    offset: np.ndarray  # (K,) global start of each path
    total: np.ndarray  # (K,) path lengths
    stop_s: np.ndarray  # global, sorted (paths are laid out in order)
    stop_path: np.ndarray
    stop_node: np.ndarray
    stop_group: np.ndarray
    arc_s0: np.ndarray  # global start of each turn
    arc_len: np.ndarray
    arc_kappa: np.ndarray  # peak |curvature| of the turn
    arc_path: np.ndarray

    @staticmethod
    def from_specs(specs: list[PathSpec], gap: float = 1000.0) -> PathSet:
        offs, o = [], 0.0
        for sp in specs:
            offs.append(o)
            o += sp.total + gap
        offs_a = np.array(offs)

        def cat(name):
            return np.concatenate([getattr(sp, name) for sp in specs])

        s0 = np.concatenate([sp.s0 + off for sp, off in zip(specs, offs_a, strict=True)])
        stop_s = np.concatenate([sp.stop_s + off for sp, off in zip(specs, offs_a, strict=True)])
        stop_path = np.concatenate(
            [np.full(len(sp.stop_s), i, np.int64) for i, sp in enumerate(specs)]
        )
        kappa = cat("kappa")
        lens = cat("length")
        path_of_piece = np.concatenate(
            [np.full(len(sp.s0), i, np.int64) for i, sp in enumerate(specs)]
        )
        # Turns = runs of consecutive curved pieces; speed limits use each turn's peak curvature.
        curved = np.abs(kappa) > 0
        first = curved & ~np.concatenate(
            [[False], curved[:-1] & (path_of_piece[1:] == path_of_piece[:-1])]
        )
        gid = np.cumsum(first) - 1
        starts = np.flatnonzero(first)
        t_len = np.bincount(gid[curved], weights=lens[curved], minlength=len(starts))
        t_kap = np.zeros(len(starts))
        np.maximum.at(t_kap, gid[curved], np.abs(kappa[curved]))
        return PathSet(
            s0,
            cat("xy0").reshape(-1, 2),
            cat("th0"),
            kappa,
            cat("edge_key"),
            cat("along0"),
            offs_a,
            np.array([sp.total for sp in specs]),
            stop_s,
            stop_path,
            cat("stop_node"),
            cat("stop_group"),
            s0[starts],
            t_len,
            t_kap,
            path_of_piece[starts],
        )

    def piece(self, s_global: np.ndarray) -> np.ndarray:
        return np.clip(np.searchsorted(self.s0, s_global, side="right") - 1, 0, len(self.s0) - 1)

    def pose(self, s_global: np.ndarray):
        """(xy (N, 2), heading (N,), curvature (N,)) at global arc lengths."""
        i = self.piece(s_global)
        ds = s_global - self.s0[i]
        th0, kap = self.th0[i], self.kappa[i]
        th = th0 + kap * ds
        is_arc = np.abs(kap) > 1e-9
        safe = np.where(is_arc, kap, 1.0)
        dx = np.where(is_arc, (np.sin(th) - np.sin(th0)) / safe, ds * np.cos(th0))
        dy = np.where(is_arc, -(np.cos(th) - np.cos(th0)) / safe, ds * np.sin(th0))
        xy = self.xy0[i] + np.column_stack([dx, dy])
        return xy, th, kap
