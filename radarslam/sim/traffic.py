"""Moving traffic and the ego vehicle: one vectorised car-following simulation per log.

Every agent (cars both directions, cyclists, pedestrians, and the ego as agent 0) drives along its
own smooth path (:mod:`radarslam.sim.paths`) with the Intelligent Driver Model: it follows the
agent ahead on the same directed street, stops at red lights, slows for curves. Accelerations are
piecewise constant per step, so the arc length ``s(t)`` is exactly piecewise quadratic and the
position, heading, speed and yaw rate of every agent are exact at any timestamp.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from radarslam.sim.config import EgoConfig, TrafficConfig
from radarslam.sim.paths import PathSet, PathSpec, build_path
from radarslam.sim.world import (
    CYCLIST,
    MOVING_CAR,
    PEDESTRIAN,
    Boxes,
    StreetNetwork,
    path_end_directions,
    standing_path,
    standing_street,
)

_LANE_CLASS = {MOVING_CAR: 0, CYCLIST: 1, PEDESTRIAN: 2}
#: The ego starts driving this many seconds before the drive's time 0 (first scene ~1-3 s later).
EGO_START_S = 10.0


def random_walk(
    net: StreetNetwork, rng: np.random.Generator, start: tuple[int, int], length_m: float
) -> list[int]:
    """Node sequence from the directed edge ``start`` until at least ``length_m`` is covered.

    Prefers going straight and never turns back (every node has degree >= 2).
    """
    seq = [start[0], start[1]]
    covered = float(np.linalg.norm(net.nodes[start[1]] - net.nodes[start[0]]))
    while covered < length_m:
        prev, cur = seq[-2], seq[-1]
        d_in = net.nodes[cur] - net.nodes[prev]
        th_in = np.arctan2(d_in[1], d_in[0])
        options = [n for n in net.neighbours(cur) if n != prev] or [prev]
        weights = []
        for n in options:
            d = net.nodes[n] - net.nodes[cur]
            turn = abs((np.arctan2(d[1], d[0]) - th_in + np.pi) % (2 * np.pi) - np.pi)
            weights.append(3.0 if turn < np.pi / 4 else 1.0)
        w = np.array(weights) / sum(weights)
        nxt = options[int(rng.choice(len(options), p=w))]
        covered += float(np.linalg.norm(net.nodes[nxt] - net.nodes[cur]))
        seq.append(nxt)
    return seq


@dataclass
class AgentParams:
    cls: np.ndarray  # int8
    v0: np.ndarray
    length: np.ndarray
    width: np.ndarray
    a_max: np.ndarray
    b_comf: np.ndarray
    headway_s: np.ndarray
    min_gap_m: np.ndarray
    obey_lights: np.ndarray
    lane_class: np.ndarray


@dataclass
class EgoMotion:
    """Ego (rear axle) state at arbitrary times, vectorised."""

    xy: np.ndarray
    yaw: np.ndarray
    v_fwd_mps: np.ndarray
    v_lat_mps: np.ndarray
    yaw_rate_radps: np.ndarray


class TrafficSim:
    """Result of the per-log simulation: query agent states at any time in [t0, t_end]."""

    def __init__(
        self,
        paths: PathSet,
        params: AgentParams,
        t0: float,
        dt: float,
        s: np.ndarray,
        v: np.ndarray,
        a: np.ndarray,
        ego_index: int | None,
    ):
        self.paths, self.params, self.t0, self.dt = paths, params, t0, dt
        self.s, self.v, self.a = s, v, a  # (steps, agents)
        self.ego_index = ego_index

    def _state(self, t: float | np.ndarray, agents: np.ndarray | slice):
        k = np.clip(
            np.floor((np.asarray(t) - self.t0) / self.dt).astype(np.int64), 0, len(self.s) - 1
        )
        tau = np.asarray(t) - (self.t0 + k * self.dt)
        s = self.s[k, agents] + self.v[k, agents] * tau + 0.5 * self.a[k, agents] * tau * tau
        v = self.v[k, agents] + self.a[k, agents] * tau
        return s, np.maximum(v, 0.0)

    def boxes(self, t: float) -> Boxes:
        """All non-ego agents at time t (world frame)."""
        idx = np.arange(len(self.params.cls))
        if self.ego_index is not None:
            idx = idx[idx != self.ego_index]
        s, v = self._state(t, idx)
        xy, th, _ = self.paths.pose(s)
        vel = v[:, None] * np.column_stack([np.cos(th), np.sin(th)])
        p = self.params
        moving_cls = p.cls[idx] != PEDESTRIAN
        return Boxes(
            xy,
            th,
            p.length[idx],
            p.width[idx],
            vel,
            p.cls[idx],
            (v < 0.1) & moving_cls,
            idx.astype(np.int64),
        )

    def ego(self, t: np.ndarray) -> EgoMotion:
        t = np.asarray(t, dtype=np.float64)
        k = np.clip(np.floor((t - self.t0) / self.dt).astype(np.int64), 0, len(self.s) - 1)
        tau = t - (self.t0 + k * self.dt)
        e = self.ego_index
        s = self.s[k, e] + self.v[k, e] * tau + 0.5 * self.a[k, e] * tau * tau
        v = np.maximum(self.v[k, e] + self.a[k, e] * tau, 0.0)
        xy, th, kap = self.paths.pose(s)
        return EgoMotion(xy, th, v, np.zeros_like(v), kap * v)


def _params(
    cls_list: list[int],
    rng: np.random.Generator,
    tcfg: TrafficConfig,
    ego_cfg: EgoConfig | None,
    ego_v0: float | None,
) -> AgentParams:
    n = len(cls_list)
    cls = np.array(cls_list, np.int8)
    v0 = np.empty(n)
    length, width = np.empty(n), np.empty(n)
    car, cyc, ped = cls == MOVING_CAR, cls == CYCLIST, cls == PEDESTRIAN
    v0[car] = rng.uniform(*tcfg.car_speed_mps, car.sum())
    v0[cyc] = rng.uniform(*tcfg.cyclist_speed_mps, cyc.sum())
    v0[ped] = rng.uniform(*tcfg.pedestrian_speed_mps, ped.sum())
    is_bus = car & (rng.uniform(0, 1, n) < 0.06)
    length[car] = rng.uniform(4.2, 5.3, car.sum())
    width[car] = rng.uniform(1.75, 2.0, car.sum())
    length[is_bus] = rng.uniform(9.0, 12.0, is_bus.sum())
    width[is_bus] = 2.5
    length[cyc], width[cyc] = 1.8, 0.6
    length[ped], width[ped] = 0.5, 0.6
    a_max = np.where(car, 1.5, np.where(cyc, 1.0, 0.8))
    b_comf = np.where(ped, 1.0, 2.5)
    headway = np.where(ped, 0.8, 1.3)
    gap = np.where(ped, 0.6, 2.2)
    obey = ~ped
    if ego_v0 is not None and ego_cfg is not None:
        v0[0] = ego_v0
        length[0], width[0] = 4.8, 1.9
        a_max[0], b_comf[0] = ego_cfg.max_accel_mps2, ego_cfg.comfort_decel_mps2
    lane = np.array([_LANE_CLASS[int(c)] for c in cls], np.int64)
    return AgentParams(cls, v0, length, width, a_max, b_comf, headway, gap, obey, lane)


def simulate_traffic(
    net: StreetNetwork,
    tcfg: TrafficConfig,
    ego_cfg: EgoConfig,
    rng: np.random.Generator,
    t_end_s: float,
    ego_route: list[int] | None,
    ego_start_along_m: float,
    ego_v0: float,
    facade_offset_m: float,
    region: tuple[float, float, float, float],
    dt: float = 0.1,
) -> TrafficSim:
    """Spawn agents in ``region`` and simulate from ``-warmup_s`` to ``t_end_s``."""
    t0 = -tcfg.warmup_s
    horizon = t_end_s - t0 + 5.0
    specs: list[PathSpec] = []
    cls_list: list[int] = []
    if ego_route is not None:
        specs.append(
            build_path(
                net,
                ego_route,
                1.75,
                ego_cfg.right_turn_radius_m,
                ego_cfg.left_turn_radius_m,
                facade_offset_m - 0.5,
                ego_start_along_m,
            )
        )
        cls_list.append(MOVING_CAR)
    xmin, ymin, xmax, ymax = region
    inside = np.all((net.nodes >= [xmin, ymin]) & (net.nodes <= [xmax, ymax]), axis=1)
    cand = [int(e) for e in range(len(net.edges)) if inside[net.edges[e]].all()]
    if not cand:
        cand = list(range(len(net.edges)))
    lengths = np.linalg.norm(net.nodes[net.edges[cand, 1]] - net.nodes[net.edges[cand, 0]], axis=1)
    km = float(lengths.sum()) / 1000.0
    p_edge = lengths / lengths.sum()
    plan = (
        (MOVING_CAR, tcfg.car_density_per_km * 2, tcfg.car_speed_mps[1], 1.75, 7.0, 12.0),
        (CYCLIST, tcfg.cyclist_density_per_km * 2, tcfg.cyclist_speed_mps[1], 3.4, 5.0, 9.0),
        (
            PEDESTRIAN,
            tcfg.pedestrian_density_per_km * 2,
            tcfg.pedestrian_speed_mps[1],
            facade_offset_m - 2.0,
            1.5,
            1.5,
        ),
    )
    for cls, density, vmax, offset, r_right, r_left in plan:
        count = int(rng.poisson(density * km))
        for _ in range(count):
            e = cand[int(rng.choice(len(cand), p=p_edge))]
            a, b = (int(x) for x in net.edges[e])
            if rng.uniform() < 0.5:
                a, b = b, a
            seq = random_walk(net, rng, (a, b), vmax * horizon * 1.1 + 200.0)
            elen = float(np.linalg.norm(net.nodes[b] - net.nodes[a]))
            start = float(rng.uniform(0, max(elen - 2 * facade_offset_m, 1.0)))
            specs.append(
                build_path(net, seq, offset, r_right, r_left, facade_offset_m - 0.5, start)
            )
            cls_list.append(cls)
    if ego_route is not None and tcfg.route_density_per_km > 0:
        # Dense traffic around the ego: cars entering its route (same way and oncoming).
        pts = net.nodes[ego_route]
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        km_route = float(seg[: max(len(seg) * 2 // 3, 1)].sum()) / 1000.0
        for rev in (False, True):
            seq_all = ego_route[::-1] if rev else ego_route
            n_edges = len(seq_all) - 1
            for _ in range(int(rng.poisson(tcfg.route_density_per_km * km_route))):
                i = int(rng.integers(n_edges // 3 if rev else 0, max(n_edges * 2 // 3, 1)))
                seq = seq_all[i:]
                if len(seq) < 2:
                    continue
                pts_s = net.nodes[seq]
                if np.linalg.norm(np.diff(pts_s, axis=0), axis=1).sum() < 300.0:
                    seq = random_walk(net, rng, (seq[-2], seq[-1]), 2000.0)
                elen = float(np.linalg.norm(net.nodes[seq[1]] - net.nodes[seq[0]]))
                start = float(rng.uniform(0, max(elen - 2 * facade_offset_m, 1.0)))
                specs.append(build_path(net, seq, 1.75, 7.0, 12.0, facade_offset_m - 0.5, start))
                cls_list.append(MOVING_CAR)
    paths = PathSet.from_specs(specs)
    ego_index = 0 if ego_route is not None else None
    params = _params(cls_list, rng, tcfg, ego_cfg, ego_v0 if ego_route is not None else None)
    return _run(net, paths, params, ego_cfg, t0, t_end_s + 2.0, dt, ego_index, tcfg.signals)


def _run(
    net,
    paths: PathSet,
    p: AgentParams,
    ego_cfg: EgoConfig,
    t0: float,
    t_end: float,
    dt: float,
    ego_index: int | None,
    signals: bool = True,
) -> TrafficSim:
    n = len(p.cls)
    steps = int(np.ceil((t_end - t0) / dt)) + 1
    s = paths.offset.copy()
    v = p.v0 * 0.5
    if ego_index is not None:
        v[ego_index] = 0.0
    s_hist = np.empty((steps, n))
    v_hist = np.empty((steps, n))
    a_hist = np.empty((steps, n))
    end = paths.offset + paths.total - 1.0
    n_nodes = len(net.nodes)
    lane_offset = p.lane_class * (n_nodes * n_nodes)
    sqrt_ab = 2.0 * np.sqrt(p.a_max * p.b_comf)
    a_lat = ego_cfg.max_lateral_accel_mps2
    stops = ego_cfg.stops
    agent_ids = np.arange(n)
    for k in range(steps):
        t = t0 + k * dt
        i = paths.piece(s)
        key = paths.edge_key[i] + lane_offset
        along = paths.along0[i] + (s - paths.s0[i])
        # Leader on the same directed street (and lane class): next along the street.
        order = np.lexsort((along, key))
        ks, al = key[order], along[order]
        same = np.zeros(n, bool)
        same[:-1] = ks[1:] == ks[:-1]
        nxt = np.roll(order, -1)
        gap = np.full(n, np.inf)
        dv = np.zeros(n)
        gap[order[same]] = (
            al[1:][same[:-1]]
            - al[:-1][same[:-1]]
            - 0.5 * (p.length[order[same]] + p.length[nxt[same]])
        )
        dv[order[same]] = v[order[same]] - v[nxt[same]]
        # Red lights: a standing virtual leader at the stop line.
        j = np.searchsorted(paths.stop_s, s - 0.3)
        jc = np.minimum(j, max(len(paths.stop_s) - 1, 0))
        if len(paths.stop_s):
            valid = (j < len(paths.stop_s)) & (paths.stop_path[jc] == agent_ids) & p.obey_lights
            valid &= signals
            node = paths.stop_node[jc]
            cyc = net.light_cycle_s[node]
            tau = (t + net.light_phase_s[node]) % cyc
            half = cyc / 2
            green = np.where(
                paths.stop_group[jc] == 0, tau < half - 3.0, (tau >= half) & (tau < cyc - 3.0)
            )
            d_stop = paths.stop_s[jc] - s
            can_stop = v * v / (2 * np.maximum(d_stop, 0.1)) < 4.0
            red = valid & ~green & can_stop & (d_stop < 80.0)
            use = red & (d_stop + 0.5 * p.length < gap)
            gap = np.where(use, np.maximum(d_stop, 0.05), gap)
            dv = np.where(use, v, dv)
        # IDM.
        v0 = p.v0.copy()
        ia = np.searchsorted(paths.arc_s0, s, side="right") - 1
        iac = np.clip(ia, 0, max(len(paths.arc_s0) - 1, 0))
        a_curve = np.full(n, np.inf)
        if len(paths.arc_s0):
            on_arc = (
                (ia >= 0)
                & (paths.arc_path[iac] == agent_ids)
                & (s < paths.arc_s0[iac] + paths.arc_len[iac])
            )
            vlim = np.sqrt(a_lat / np.abs(paths.arc_kappa[iac]))
            v0 = np.where(on_arc, np.minimum(v0, vlim), v0)
            nx_ = np.minimum(ia + 1, len(paths.arc_s0) - 1)
            ahead = (paths.arc_path[nx_] == agent_ids) & (paths.arc_s0[nx_] > s)
            vlim_n = np.sqrt(a_lat / np.abs(paths.arc_kappa[nx_]))
            d_arc = np.maximum(paths.arc_s0[nx_] - s, 0.5)
            a_req = (vlim_n**2 - v * v) / (2 * d_arc)
            # Brake for the curve only once a firm deceleration is needed (as drivers do).
            a_curve = np.where(ahead & (a_req < -0.8), a_req, np.inf)
        s_star = p.min_gap_m + v * p.headway_s + v * dv / sqrt_ab
        s_star = np.maximum(s_star, p.min_gap_m)
        free = 1.0 - (v / np.maximum(v0, 0.1)) ** 4
        inter = np.where(np.isfinite(gap), (s_star / np.maximum(gap, 0.05)) ** 2, 0.0)
        acc = p.a_max * (free - inter)
        acc = np.minimum(acc, a_curve)
        acc = np.clip(acc, -7.0, p.a_max)
        if ego_index is not None:
            td = t
            if t < -EGO_START_S:  # the ego waits while the traffic warms up
                acc[ego_index] = -v[ego_index] / dt
            for stop in stops:
                if stop.at_s <= td < stop.at_s + stop.duration_s:
                    acc[ego_index] = -ego_cfg.comfort_decel_mps2
        acc = np.maximum(acc, -v / dt)  # never reverse
        at_end = s >= end
        acc[at_end] = -v[at_end] / dt
        s_hist[k], v_hist[k], a_hist[k] = s, v, acc
        s = s + v * dt + 0.5 * acc * dt * dt
        v = np.maximum(v + acc * dt, 0.0)
    return TrafficSim(paths, p, t0, dt, s_hist, v_hist, a_hist, ego_index)


#: Bumper to bumper at a standstill, in the queue on a given trajectory's street.
_STANDSTILL_GAP_M = 2.0
#: The ego's bumpers from its rear axle (nuScenes' car: the front radar sits at 3.41 m).
_EGO_FRONT_M, _EGO_REAR_M = 3.5, 0.7
#: How far ahead and behind (in time headway) same-direction cars are placed.
_SAME_WAY_HORIZON_S = 40.0


class _PathLine:
    """A driven path as a function of arc length, continued straight beyond both ends as
    :func:`radarslam.sim.world.street_polyline` continues its street."""

    def __init__(self, s: np.ndarray, xy: np.ndarray, yaw: np.ndarray):
        self.s, self.xy, self.yaw = s, xy, yaw
        self.end_yaw = [float(np.arctan2(d[1], d[0])) for d in path_end_directions(xy)]

    def pose(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        s = np.asarray(s, dtype=np.float64)
        xy = np.column_stack([np.interp(s, self.s, self.xy[:, k]) for k in range(2)])
        yaw = np.interp(s, self.s, self.yaw)
        for end, beyond in ((0, s < self.s[0]), (-1, s > self.s[-1])):
            if np.any(beyond):
                th = self.end_yaw[end]
                d = np.array([np.cos(th), np.sin(th)])
                xy[beyond] = self.xy[end] + (s[beyond] - self.s[end])[:, None] * d
                yaw[beyond] = th
        return xy, yaw


@dataclass
class PathTraffic:
    """Cars on the street a given trajectory drives (``--trajectory``), where the city's
    network traffic never comes: the drive's own street otherwise has no car ahead, behind or
    oncoming, which real drives always have.

    Same-way cars ride in the ego's lane as time-shifted copies of its motion (a car
    ``tau`` s ahead is where the ego will be ``tau`` s later, plus its place in the queue,
    bumper to bumper 2 m apart at a standstill): they brake, stop and start with the ego as a
    queue at a light does, and never touch it or each other.
    Oncoming cars keep a constant speed in the lane to the left of the path.
    """

    line: _PathLine
    t_grid: np.ndarray  # the ego's arc length s(t) and speed, tabulated
    s_grid: np.ndarray
    v_grid: np.ndarray
    shift_s: np.ndarray  # (A,) same-way cars: time shift (+ ahead, - behind)
    queue_m: np.ndarray  # (A,) signed queue offset
    oncoming_s0: np.ndarray  # (B,) arc length at t = 0
    oncoming_v: np.ndarray  # (B,) m/s
    oncoming_offset_m: float
    length: np.ndarray  # (A + B,)
    width: np.ndarray

    def boxes(self, t: float) -> Boxes:
        tq = t + self.shift_s
        s_same = np.interp(tq, self.t_grid, self.s_grid) + self.queue_m
        v_same = np.interp(tq, self.t_grid, self.v_grid)
        s_on = self.oncoming_s0 - self.oncoming_v * t
        xy_a, yaw_a = self.line.pose(s_same)
        xy_b, yaw_b = self.line.pose(s_on)
        left = np.column_stack([-np.sin(yaw_b), np.cos(yaw_b)])
        xy_b = xy_b + self.oncoming_offset_m * left
        yaw_b = yaw_b + np.pi
        xy = np.vstack([xy_a, xy_b])
        yaw = np.concatenate([yaw_a, yaw_b])
        v = np.concatenate([v_same, self.oncoming_v])
        n = len(v)
        return Boxes(
            xy,
            yaw,
            self.length,
            self.width,
            v[:, None] * np.column_stack([np.cos(yaw), np.sin(yaw)]),
            np.full(n, MOVING_CAR, np.int8),
            v < 0.1,
            np.arange(n, dtype=np.int64) + 2_000_000,
        )


def path_traffic(
    ego_fn: Callable[[np.ndarray], EgoMotion],
    duration_s: float,
    tcfg: TrafficConfig,
    rng: np.random.Generator,
    t_end_s: float,
) -> PathTraffic:
    """:class:`PathTraffic` for an ego driven by ``ego_fn(t) -> EgoMotion`` over
    ``[0, duration_s]`` (held at its end states outside), at the city's car densities
    (``car_density_per_km`` + ``route_density_per_km`` per direction)."""
    dt = 0.05
    t_grid = np.arange(-_SAME_WAY_HORIZON_S - 5.0, t_end_s + _SAME_WAY_HORIZON_S + 5.0, dt)
    ego = ego_fn(np.clip(t_grid, 0.0, duration_s))
    v = np.hypot(ego.v_fwd_mps, ego.v_lat_mps)
    s = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * dt)])
    inside = (t_grid >= 0.0) & (t_grid <= duration_s)
    s_in, xy_in, yaw_in = s[inside], ego.xy[inside], ego.yaw[inside]
    moved = np.concatenate([[True], np.diff(s_in) > 1e-3])
    s_in, xy_in, yaw_in = s_in[moved], xy_in[moved], yaw_in[moved]
    if standing_path(xy_in):
        # Standing still: the street of street_polyline, along x through the poses.
        xy_in = standing_street(xy_in)
        s_in = s_in[0] + np.array([-0.5, 0.5]) * np.linalg.norm(xy_in[1] - xy_in[0])
        yaw_in = np.zeros(2)
    line = _PathLine(s_in, xy_in, yaw_in)

    density = tcfg.car_density_per_km + tcfg.route_density_per_km
    v_ref = 0.5 * (tcfg.car_speed_mps[0] + tcfg.car_speed_mps[1])
    shifts = []  # ahead, nearest first, then behind, nearest first
    if density > 0:
        mean_headway_s = 1000.0 / (density * v_ref)
        for sign in (1.0, -1.0):
            tau = 0.0
            while True:
                tau += 1.0 + rng.exponential(mean_headway_s)
                if tau > _SAME_WAY_HORIZON_S:
                    break
                shifts.append(sign * tau)
    reach = 300.0 + tcfg.car_speed_mps[1] * t_end_s
    lo, hi = s_in[0] - 300.0, s_in[-1] + reach
    n_on = int(rng.poisson(tcfg.car_density_per_km * (hi - lo) / 1000.0))
    on_s0 = rng.uniform(lo, hi, n_on)
    on_v = rng.uniform(*tcfg.car_speed_mps, n_on)
    n = len(shifts) + n_on
    length = rng.uniform(4.2, 5.3, n)
    width = rng.uniform(1.75, 2.0, n)
    bus = rng.uniform(0, 1, n) < 0.06
    length[bus], width[bus] = rng.uniform(9.0, 12.0, int(bus.sum())), 2.5
    # Each car's place in the queue (its centre from the ego's rear axle at a standstill):
    # bumper to bumper, whatever the cars' lengths.
    queue = np.zeros(len(shifts))
    for sign, edge in ((1.0, _EGO_FRONT_M), (-1.0, _EGO_REAR_M)):
        for i in (i for i, tau in enumerate(shifts) if np.sign(tau) == sign):
            queue[i] = sign * (edge + _STANDSTILL_GAP_M + 0.5 * length[i])
            edge += _STANDSTILL_GAP_M + length[i]
    return PathTraffic(
        line,
        t_grid,
        s,
        v,
        np.array(shifts, dtype=np.float64),
        queue,
        on_s0,
        on_v,
        3.0,
        length,
        width,
    )
