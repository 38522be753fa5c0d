"""The 2-D synthetic city: street network, facades, poles, trees, guard rails, parking slots.

Everything is generated once from the seed, so every log (day) drives through the same static
world; only the parked cars (seeded per day) and the traffic change between days.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import numpy as np

from radarslam.sim.config import CityConfig

# Object classes (shared with the radar model and the sidecar).
FACADE, CORNER, POLE, TREE, VEGETATION, GUARDRAIL, PARKED_CAR = 0, 1, 2, 3, 4, 5, 6
MOVING_CAR, CYCLIST, PEDESTRIAN, CLUTTER, GHOST = 7, 8, 9, 10, 11
CLASS_NAMES = (
    "facade",
    "corner",
    "pole",
    "tree",
    "vegetation",
    "guardrail",
    "parked_car",
    "car",
    "cyclist",
    "pedestrian",
    "clutter",
    "ghost",
)


@dataclass
class Scatterers:
    """Point scatterers in the world frame with an aspect-dependent radar cross-section.

    ``rcs = rcs_dbsm + spec_gain_db * exp(-(incidence / lobe_rad)^2)`` for scatterers that have a
    normal (|n| = 1); isotropic ones have n = 0 and are visible from every side.
    """

    xy: np.ndarray  # (N, 2) float64
    rcs_dbsm: np.ndarray  # (N,) diffuse part
    cls: np.ndarray  # (N,) int8 class
    normal: np.ndarray  # (N, 2) unit outward normal, or 0 for isotropic
    lobe_rad: np.ndarray  # (N,) specular lobe width
    spec_gain_db: np.ndarray  # (N,)
    p_scale: np.ndarray  # (N,) detection-probability multiplier (flicker of vegetation)
    jitter_m: np.ndarray  # (N,) per-detection position jitter (diffuse canopies)

    def __len__(self) -> int:
        return len(self.xy)

    @staticmethod
    def empty() -> Scatterers:
        return Scatterers(
            np.zeros((0, 2)),
            np.zeros(0),
            np.zeros(0, np.int8),
            np.zeros((0, 2)),
            np.ones(0),
            np.zeros(0),
            np.ones(0),
            np.zeros(0),
        )

    @staticmethod
    def concat(parts: list[Scatterers]) -> Scatterers:
        parts = [p for p in parts if len(p)]
        if not parts:
            return Scatterers.empty()
        return Scatterers(
            *[
                np.concatenate([getattr(p, f) for p in parts])
                for f in (
                    "xy",
                    "rcs_dbsm",
                    "cls",
                    "normal",
                    "lobe_rad",
                    "spec_gain_db",
                    "p_scale",
                    "jitter_m",
                )
            ]
        )

    def subset(self, mask: np.ndarray) -> Scatterers:
        return Scatterers(
            self.xy[mask],
            self.rcs_dbsm[mask],
            self.cls[mask],
            self.normal[mask],
            self.lobe_rad[mask],
            self.spec_gain_db[mask],
            self.p_scale[mask],
            self.jitter_m[mask],
        )


def _make(xy, rcs, cls, normal=None, lobe=0.3, spec=0.0, p_scale=1.0, jitter=0.0) -> Scatterers:
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    n = len(xy)

    def full(v):
        return np.broadcast_to(np.asarray(v, dtype=np.float64), (n,)).copy()

    nrm = np.zeros((n, 2)) if normal is None else np.broadcast_to(normal, (n, 2)).astype(float)
    return Scatterers(
        xy,
        full(rcs),
        np.full(n, cls, np.int8),
        nrm.copy(),
        full(lobe),
        full(spec),
        full(p_scale),
        full(jitter),
    )


@dataclass
class StreetNetwork:
    nodes: np.ndarray  # (N, 2)
    edges: np.ndarray  # (E, 2) undirected, node indices
    has_light: np.ndarray  # (N,) bool
    light_cycle_s: np.ndarray  # (N,)
    light_phase_s: np.ndarray  # (N,)
    boundary_edge: np.ndarray  # (E,) bool: on the outer ring
    adjacency: list[list[int]] = field(default_factory=list)

    def neighbours(self, node: int) -> list[int]:
        return self.adjacency[node]


@dataclass
class ParkingSlots:
    xy: np.ndarray  # (S, 2) slot centres
    yaw: np.ndarray  # (S,) along the street
    long_term: np.ndarray  # (S,) bool: the same car is parked here on most days
    lt_len: np.ndarray
    lt_wid: np.ndarray
    lt_flip: np.ndarray  # long-term car heading flipped by pi


@dataclass
class Boxes:
    """Oriented rectangles (cars, cyclists, pedestrians) at one instant."""

    xy: np.ndarray  # (K, 2) centre
    yaw: np.ndarray  # (K,)
    length: np.ndarray
    width: np.ndarray
    velocity: np.ndarray  # (K, 2) over ground, world frame
    cls: np.ndarray  # (K,) int8
    stopped: np.ndarray  # (K,) bool: a traffic participant standing still (dyn_prop 7)
    obj_id: np.ndarray  # (K,) int: stable identity (instance)

    def __len__(self) -> int:
        return len(self.xy)

    @staticmethod
    def empty() -> Boxes:
        z = np.zeros(0)
        return Boxes(
            np.zeros((0, 2)),
            z,
            z,
            z,
            np.zeros((0, 2)),
            np.zeros(0, np.int8),
            np.zeros(0, bool),
            np.zeros(0, np.int64),
        )

    @staticmethod
    def concat(parts: list[Boxes]) -> Boxes:
        parts = [p for p in parts if len(p)]
        if not parts:
            return Boxes.empty()
        return Boxes(
            *[
                np.concatenate([getattr(p, f) for p in parts])
                for f in ("xy", "yaw", "length", "width", "velocity", "cls", "stopped", "obj_id")
            ]
        )

    def subset(self, mask) -> Boxes:
        return Boxes(
            self.xy[mask],
            self.yaw[mask],
            self.length[mask],
            self.width[mask],
            self.velocity[mask],
            self.cls[mask],
            self.stopped[mask],
            self.obj_id[mask],
        )


@dataclass
class StaticWorld:
    config: CityConfig
    network: StreetNetwork
    scatterers: Scatterers
    occluders: np.ndarray  # (M, 4) x0 y0 x1 y1: facades (block radar waves)
    reflectors: np.ndarray  # (R, 4): facades + guard rails (multipath mirrors)
    parking: ParkingSlots
    buildings: list[np.ndarray]  # facade polylines for the sidecar / plots
    bounds: tuple[float, float, float, float]  # xmin ymin xmax ymax


def _unit(v):
    return v / np.linalg.norm(v)


def _left(d):
    return np.array([-d[1], d[0]])


def build_network(cfg: CityConfig, rng: np.random.Generator, light_cycle=(45.0, 75.0)):
    nx, ny = cfg.n_blocks_x, cfg.n_blocks_y
    xs = np.concatenate([[0.0], np.cumsum(rng.uniform(cfg.block_min_m, cfg.block_max_m, nx))])
    ys = np.concatenate([[0.0], np.cumsum(rng.uniform(cfg.block_min_m, cfg.block_max_m, ny))])
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    nodes = np.column_stack([gx.ravel(), gy.ravel()]) + np.asarray(cfg.origin_m)
    nodes += rng.uniform(-cfg.node_jitter_m, cfg.node_jitter_m, nodes.shape)

    def nid(i, j):
        return i * (ny + 1) + j

    edge_list: list[tuple[int, int]] = []
    on_boundary: list[bool] = []
    for i in range(nx + 1):
        for j in range(ny + 1):
            if i < nx:
                edge_list.append((nid(i, j), nid(i + 1, j)))
                on_boundary.append(j in (0, ny))
            if j < ny:
                edge_list.append((nid(i, j), nid(i, j + 1)))
                on_boundary.append(i in (0, nx))
    edges = np.array(edge_list)
    boundary = np.array(on_boundary)
    keep = np.ones(len(edges), bool)
    n_nodes = len(nodes)
    degree = np.bincount(edges.ravel(), minlength=n_nodes)
    # Irregularity: drop interior edges while every node keeps degree >= 2 and the graph stays
    # connected (so routes exist everywhere and there are no dead ends).
    n_drop = round(cfg.drop_edge_fraction * (~boundary).sum())
    for e in rng.permutation(np.flatnonzero(~boundary)):
        if n_drop <= 0:
            break
        a, b = edges[e]
        if degree[a] <= 2 or degree[b] <= 2:
            continue
        keep[e] = False
        if _connected(n_nodes, edges[keep]):
            degree[a] -= 1
            degree[b] -= 1
            n_drop -= 1
        else:
            keep[e] = True
    edges, boundary = edges[keep], boundary[keep]
    adjacency: list[list[int]] = [[] for _ in range(n_nodes)]
    for a, b in edges:
        adjacency[a].append(int(b))
        adjacency[b].append(int(a))
    degree = np.array([len(a) for a in adjacency])
    has_light = degree >= 3
    cycle = rng.uniform(light_cycle[0], light_cycle[1], n_nodes)
    phase = rng.uniform(0, 1, n_nodes) * cycle
    return StreetNetwork(nodes, edges, has_light, cycle, phase, boundary, adjacency)


def _connected(n_nodes: int, edges: np.ndarray) -> bool:
    adj: list[list[int]] = [[] for _ in range(n_nodes)]
    for a, b in edges:
        adj[a].append(b)
        adj[b].append(a)
    seen = np.zeros(n_nodes, bool)
    stack = [0]
    seen[0] = True
    while stack:
        u = stack.pop()
        for v in adj[u]:
            if not seen[v]:
                seen[v] = True
                stack.append(v)
    return bool(seen.all())


def _line_intersection(p, d, q, e):
    """Intersection of p + t d and q + s e (None when parallel)."""
    den = d[0] * e[1] - d[1] * e[0]
    if abs(den) < 1e-9:
        return None
    w = q - p
    t = (w[0] * e[1] - w[1] * e[0]) / den
    return p + t * d


class _CityBuilder:
    def __init__(self, cfg: CityConfig, rng: np.random.Generator, net: StreetNetwork):
        self.cfg, self.rng, self.net = cfg, rng, net
        self.parts: list[Scatterers] = []
        self.occluders: list[tuple[float, float, float, float]] = []
        self.rails: list[tuple[float, float, float, float]] = []
        self.buildings: list[np.ndarray] = []

    # --- buildings ---------------------------------------------------------------------------
    def facade_row(self, a: np.ndarray, b: np.ndarray, outward: np.ndarray) -> None:
        """Buildings with gaps along the street-side line a->b (outward normal towards street)."""
        cfg, rng = self.cfg, self.rng
        d = b - a
        length = float(np.linalg.norm(d))
        if length < 3.0:
            return
        d = d / length
        inward = -outward
        pos = rng.uniform(0.0, cfg.gap_max_m * 0.5)
        while pos < length - 2.0:
            blen = min(rng.uniform(cfg.building_len_min_m, cfg.building_len_max_m), length - pos)
            setback = rng.uniform(0.0, cfg.facade_setback_jitter_m)
            p0 = a + d * pos + inward * setback
            p1 = a + d * (pos + blen) + inward * setback
            depth = rng.uniform(8.0, 18.0)
            # Facade plus both side walls: the side walls are what the radar sees through gaps.
            poly = np.array([p0 + inward * depth, p0, p1, p1 + inward * depth])
            self.buildings.append(poly)
            for s0, s1 in ((poly[0], poly[1]), (poly[1], poly[2]), (poly[2], poly[3])):
                self.occluders.append((*s0, *s1))
            self.wall_scatterers(p0, p1, outward)
            self.wall_scatterers(poly[0], p0, -d)
            self.wall_scatterers(p1, poly[3], d)
            corners = np.array([p0, p1])
            cn = np.array([_unit(outward - d), _unit(outward + d)])
            self.parts.append(
                Scatterers(
                    corners,
                    rng.normal(18.0, 5.0, 2),
                    np.full(2, CORNER, np.int8),
                    cn,
                    np.full(2, np.deg2rad(40.0)),
                    np.full(2, 6.0),
                    rng.uniform(0.7, 1.0, 2),
                    np.zeros(2),
                )
            )
            pos += blen + rng.uniform(cfg.gap_min_m, cfg.gap_max_m)

    def wall_scatterers(self, p0: np.ndarray, p1: np.ndarray, normal: np.ndarray) -> None:
        cfg, rng = self.cfg, self.rng
        seg = p1 - p0
        length = float(np.linalg.norm(seg))
        n = max(1, int(length / cfg.facade_scatter_spacing_m))
        t = (np.arange(n) + rng.uniform(0.2, 0.8, n)) / n
        xy = p0 + t[:, None] * seg
        self.parts.append(
            _make(
                xy,
                rng.normal(5.5, 5.0, n),
                FACADE,
                normal,
                lobe=np.deg2rad(10.0),
                spec=rng.uniform(5.0, 18.0, n),
                p_scale=rng.uniform(0.8, 1.0, n),
            )
        )

    def block(self, corners: np.ndarray, park: bool) -> None:
        """One city block between four street nodes (counter-clockwise corners)."""
        cfg, _rng = self.cfg, self.rng
        off = cfg.facade_offset_m
        m = len(corners)
        lines = []
        for k in range(m):
            a, b = corners[k], corners[(k + 1) % m]
            d = _unit(b - a)
            inward = _left(d)  # ccw polygon: the interior is on the left
            lines.append((a + inward * off, d, inward))
        corners_in = []
        for k in range(m):
            p, d, _ = lines[k - 1]
            q, e, _ = lines[k]
            x = _line_intersection(p, d, q, e)
            corners_in.append(x if x is not None else q)
        inset = np.array(corners_in)
        for k in range(m):
            a, b = inset[k], inset[(k + 1) % m]
            outward = -lines[k][2]
            if park:
                self.hedge(a, b, outward)
            else:
                self.facade_row(a, b, outward)
        if park:
            self.park_interior(inset)

    def hedge(self, a, b, outward) -> None:
        rng = self.rng
        length = float(np.linalg.norm(b - a))
        n = max(2, int(length / 1.5))
        t = np.sort(rng.uniform(0, 1, n))
        xy = a + t[:, None] * (b - a) - outward * rng.uniform(0, 1.5, n)[:, None]
        self.parts.append(
            _make(
                xy,
                rng.normal(-6.0, 3.0, n),
                VEGETATION,
                p_scale=rng.uniform(0.15, 0.4, n),
                jitter=0.5,
            )
        )

    def park_interior(self, poly: np.ndarray) -> None:
        rng = self.rng
        lo, hi = poly.min(0), poly.max(0)
        area = float(np.prod(hi - lo))
        n = int(area / 120.0)
        xy = rng.uniform(lo, hi, (n, 2))
        self.trees(xy)

    # --- street furniture --------------------------------------------------------------------
    def trees(self, centres: np.ndarray) -> None:
        rng = self.rng
        if len(centres) == 0:
            return
        self.parts.append(
            _make(
                centres,
                rng.normal(-1.0, 3.0, len(centres)),
                TREE,
                p_scale=rng.uniform(0.3, 0.7, len(centres)),
                jitter=0.15,
            )
        )
        k = rng.integers(2, 6, len(centres))
        canopy = np.repeat(centres, k, axis=0) + rng.normal(0, 1.3, (int(k.sum()), 2))
        self.parts.append(
            _make(
                canopy,
                rng.normal(-5.5, 3.0, len(canopy)),
                VEGETATION,
                p_scale=rng.uniform(0.1, 0.4, len(canopy)),
                jitter=0.5,
            )
        )

    def street_side(self, a: np.ndarray, b: np.ndarray, right: np.ndarray, rail: bool) -> None:
        """Poles, trees and guard rails along one side of the street a->b (right = unit normal)."""
        cfg, rng = self.cfg, self.rng
        d = b - a
        length = float(np.linalg.norm(d))
        u = d / length
        clear = cfg.facade_offset_m + 2.0  # keep intersections free
        if length < 2 * clear + 5:
            return
        side = cfg.facade_offset_m - 2.5
        s = np.arange(clear, length - clear, cfg.pole_spacing_m) + rng.uniform(
            -4, 4, len(np.arange(clear, length - clear, cfg.pole_spacing_m))
        )
        xy = a + s[:, None] * u + right * side
        self.parts.append(
            _make(xy, rng.normal(7.0, 4.0, len(xy)), POLE, p_scale=rng.uniform(0.8, 1.0, len(xy)))
        )
        if rng.uniform() < cfg.tree_street_fraction:
            s = np.arange(clear, length - clear, cfg.tree_spacing_m)
            s = s + rng.uniform(-1.5, 1.5, len(s))
            self.trees(a + s[:, None] * u + right * (cfg.facade_offset_m - 3.5))
        if rail:
            r_off = 6.3
            p0, p1 = a + u * clear + right * r_off, b - u * clear + right * r_off
            self.rail(p0, p1, -right)

    def rail(self, p0: np.ndarray, p1: np.ndarray, normal: np.ndarray) -> None:
        rng = self.rng
        self.rails.append((*p0, *p1))
        length = float(np.linalg.norm(p1 - p0))
        n = max(2, int(length / 1.0))
        t = (np.arange(n) + 0.5) / n
        xy = p0 + t[:, None] * (p1 - p0)
        # A long metallic rail is a mirror: almost nothing unless seen near-perpendicular.
        self.parts.append(
            _make(
                xy,
                rng.normal(-8.0, 3.0, n),
                GUARDRAIL,
                normal,
                lobe=np.deg2rad(3.5),
                spec=rng.uniform(22.0, 30.0, n),
                p_scale=0.9,
            )
        )
        posts = xy[::2] - normal * 0.1
        self.parts.append(_make(posts, rng.normal(-4.0, 3.0, len(posts)), GUARDRAIL, p_scale=0.35))


def build_world(cfg: CityConfig, seed: int, light_cycle=(45.0, 75.0)) -> StaticWorld:
    rng = np.random.default_rng([seed, 101])
    net = build_network(cfg, rng, light_cycle)
    b = _CityBuilder(cfg, rng, net)
    nx, ny = cfg.n_blocks_x, cfg.n_blocks_y

    def nid(i, j):
        return i * (ny + 1) + j

    for i in range(nx):
        for j in range(ny):
            corners = net.nodes[[nid(i, j), nid(i + 1, j), nid(i + 1, j + 1), nid(i, j + 1)]]
            b.block(corners, park=rng.uniform() < cfg.park_block_fraction)
    # Outer ring: buildings outside three sides; the south side is a waterfront with a rail.
    ring = [
        ([nid(i, ny) for i in range(nx + 1)], "north"),
        ([nid(nx, j) for j in range(ny + 1)], "east"),
        ([nid(0, j) for j in range(ny + 1)], "west"),
        ([nid(i, 0) for i in range(nx + 1)], "south"),
    ]
    centre = net.nodes.mean(0)
    for ids, side in ring:
        for a_id, b_id in itertools.pairwise(ids):
            a, c = net.nodes[a_id], net.nodes[b_id]
            d = _unit(c - a)
            out = _left(d)
            if np.dot(out, (a + c) / 2 - centre) < 0:
                out = -out
            if side == "south":
                b.rail(a + out * 7.0, c + out * 7.0, -out)
            else:
                p, q = a + out * cfg.facade_offset_m, c + out * cfg.facade_offset_m
                b.facade_row(p - d * cfg.facade_offset_m, q + d * cfg.facade_offset_m, -out)
    # Street furniture and parking, per edge side.
    slots_xy, slots_yaw = [], []
    for e, (ia, ib) in enumerate(net.edges):
        a, c = net.nodes[ia], net.nodes[ib]
        d = _unit(c - a)
        yaw = float(np.arctan2(d[1], d[0]))
        for right in (-_left(d), _left(d)):
            outer = net.boundary_edge[e] and np.dot(right, (a + c) / 2 - centre) > 0
            rail = (not outer) and rng.uniform() < cfg.guard_rail_edge_fraction
            b.street_side(a, c, right, rail)
            if rail or outer or rng.uniform() >= cfg.parking_edge_fraction:
                continue
            length = float(np.linalg.norm(c - a))
            clear = cfg.facade_offset_m + 5.0
            s = np.arange(clear, length - clear, cfg.parking_slot_m)
            slots_xy.append(a + s[:, None] * d + right * 4.7)
            slots_yaw.append(np.full(len(s), yaw))
    sxy = np.concatenate(slots_xy) if slots_xy else np.zeros((0, 2))
    syaw = np.concatenate(slots_yaw) if slots_yaw else np.zeros(0)
    n_slots = len(sxy)
    parking = ParkingSlots(
        sxy,
        syaw,
        rng.uniform(0, 1, n_slots) < cfg.long_term_parked_fraction,
        rng.uniform(4.2, 5.3, n_slots),
        rng.uniform(1.75, 2.0, n_slots),
        rng.uniform(0, 1, n_slots) < 0.15,
    )
    occ = np.array(b.occluders, dtype=np.float64).reshape(-1, 4)
    rails = np.array(b.rails, dtype=np.float64).reshape(-1, 4)
    lo = net.nodes.min(0) - cfg.facade_offset_m - 30
    hi = net.nodes.max(0) + cfg.facade_offset_m + 30
    return StaticWorld(
        cfg,
        net,
        Scatterers.concat(b.parts),
        occ,
        np.concatenate([occ, rails]),
        parking,
        b.buildings,
        (float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])),
    )


def parked_cars(world: StaticWorld, day: int, seed: int) -> Boxes:
    """The cars parked on a given day: long-term ones (mostly the same) plus a daily draw."""
    cfg = world.config
    p = world.parking
    rng = np.random.default_rng([seed, 202, day])
    n = len(p.xy)
    occupied = np.where(
        p.long_term, rng.uniform(0, 1, n) < 0.92, rng.uniform(0, 1, n) < cfg.parking_occupancy
    )
    length = np.where(p.long_term, p.lt_len, rng.uniform(4.2, 5.3, n))
    width = np.where(p.long_term, p.lt_wid, rng.uniform(1.75, 2.0, n))
    flip = np.where(p.long_term, p.lt_flip, rng.uniform(0, 1, n) < 0.15)
    along = rng.normal(0, 0.6, n)
    lateral = rng.normal(0, 0.15, n)
    yaw = p.yaw + np.where(flip, np.pi, 0.0) + rng.normal(0, np.deg2rad(2.0), n)
    d = np.column_stack([np.cos(p.yaw), np.sin(p.yaw)])
    xy = p.xy + along[:, None] * d + lateral[:, None] * np.column_stack([-d[:, 1], d[:, 0]])
    m = occupied
    k = int(m.sum())
    return Boxes(
        xy[m],
        yaw[m],
        length[m],
        width[m],
        np.zeros((k, 2)),
        np.full(k, PARKED_CAR, np.int8),
        np.zeros(k, bool),
        np.flatnonzero(m).astype(np.int64) + 1_000_000 * (day + 1),
    )


def drivable_mask(world: StaticWorld, resolution_m: float) -> np.ndarray:
    """uint8 image (row 0 = north) of the roads, origin at world (0, 0) as nuScenes map masks."""
    xmax, ymax = world.bounds[2], world.bounds[3]
    w, h = int(np.ceil(xmax / resolution_m)), int(np.ceil(ymax / resolution_m))
    img = np.zeros((h, w), np.uint8)
    half = world.config.facade_offset_m - 3.0
    for ia, ib in world.network.edges:
        a, c = world.network.nodes[ia], world.network.nodes[ib]
        lo = np.floor((np.minimum(a, c) - half) / resolution_m).astype(int).clip(0)
        hi = np.ceil((np.maximum(a, c) + half) / resolution_m).astype(int)
        hi = np.minimum(hi, [w, h])
        if np.any(hi <= lo):
            continue
        px = (np.arange(lo[0], hi[0]) + 0.5) * resolution_m
        py = (np.arange(lo[1], hi[1]) + 0.5) * resolution_m
        gx, gy = np.meshgrid(px, py)
        d = c - a
        t = np.clip(((gx - a[0]) * d[0] + (gy - a[1]) * d[1]) / float(d @ d), 0, 1)
        dist = np.hypot(gx - a[0] - t * d[0], gy - a[1] - t * d[1])
        rows = h - 1 - np.arange(lo[1], hi[1])
        sub = img[rows[:, None], np.arange(lo[0], hi[0])[None, :]]
        img[rows[:, None], np.arange(lo[0], hi[0])[None, :]] = np.where(dist <= half, 255, sub)
    return img


#: How far the street of a given path continues past the drive's ends: the radars see ahead
#: and behind the drive, the front unit's far scan to 220 m.
PATH_STREET_BEYOND_M = 150.0


def standing_path(path_xy: np.ndarray) -> bool:
    """Whether a path stays within 2.5 m of its mean (a standing ego: no street direction)."""
    return bool(np.linalg.norm(path_xy - path_xy.mean(0), axis=1).max() < 2.5)


def standing_street(path_xy: np.ndarray) -> np.ndarray:
    """(2, 2) ends of the street a standing path stands in: 50 m along x through its poses."""
    centre, half = path_xy.mean(0), np.array([25.0, 0.0])
    return np.array([centre - half, centre + half])


def path_end_directions(path_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit directions in which a path leaves its first and its last pose: from the pose 10 m
    away (straight-line distance, or half the path's reach if shorter). A standing ego's poses
    jitter by centimetres in every direction, which neither the last step nor the last metres
    of arc length (jitter adds up to metres of it) can tell from a direction."""

    def leaving(xy: np.ndarray) -> np.ndarray:
        d = np.linalg.norm(xy - xy[-1], axis=1)
        far = np.flatnonzero(d >= min(10.0, 0.5 * d.max()))
        return _unit(xy[-1] - xy[far[-1]])

    return -leaving(path_xy[::-1]), leaving(path_xy)


def street_polyline(
    path_xy: np.ndarray, step_m: float, beyond_m: float = PATH_STREET_BEYOND_M
) -> tuple[np.ndarray, np.ndarray]:
    """``(points, s)``: points every ``step_m`` along the street a path drives and their arc
    length from the path's start (negative before it), continued straight for ``beyond_m``
    past both ends (:func:`path_end_directions`). A standing path (:func:`standing_path`)
    drives a 50 m street along x through its poses."""
    if standing_path(path_xy):
        path_xy = standing_street(path_xy)
    step = np.linalg.norm(np.diff(path_xy, axis=0), axis=1)
    cum = np.concatenate([[0.0], np.cumsum(step)])
    d0, d1 = path_end_directions(path_xy)
    s = np.arange(-beyond_m, cum[-1] + beyond_m + 1e-9, step_m)
    inside = np.clip(s, 0.0, cum[-1])
    pts = np.column_stack([np.interp(inside, cum, path_xy[:, k]) for k in range(2)])
    pts = pts + np.minimum(s, 0.0)[:, None] * d0 + np.maximum(s - cum[-1], 0.0)[:, None] * d1
    keep = np.concatenate([[True], np.linalg.norm(np.diff(pts, axis=0), axis=1) > 0.05 * step_m])
    return pts[keep], s[keep]


def carve_corridor(world: StaticWorld, lines: list[np.ndarray], half_width: float) -> StaticWorld:
    """``world`` without what stands within ``half_width`` of the polylines ``lines``:
    scatterers, occluders, reflectors and parking slots."""
    from scipy.spatial import cKDTree

    dense = []
    for xy in lines:
        seg = np.diff(xy, axis=0)
        n = np.maximum(np.ceil(np.linalg.norm(seg, axis=1) / 0.5).astype(int), 1)
        dense += [
            xy[i] + np.linspace(0, 1, k, endpoint=False)[:, None] * seg[i] for i, k in enumerate(n)
        ]
        dense.append(xy[-1:])
    tree = cKDTree(np.vstack(dense))

    def clear_of(xy: np.ndarray) -> np.ndarray:
        if len(xy) == 0:
            return np.zeros(0, bool)
        return np.asarray(tree.query(xy)[0] > half_width)

    def seg_keep(segs: np.ndarray) -> np.ndarray:
        if len(segs) == 0:
            return np.zeros(0, bool)
        t = np.linspace(0, 1, 9)
        pts = segs[:, None, :2] + t[None, :, None] * (segs[:, None, 2:] - segs[:, None, :2])
        return np.asarray(clear_of(pts.reshape(-1, 2)).reshape(len(segs), -1).all(1))

    p = world.parking
    k = clear_of(p.xy)
    return StaticWorld(
        world.config,
        world.network,
        world.scatterers.subset(clear_of(world.scatterers.xy)),
        world.occluders[seg_keep(world.occluders)],
        world.reflectors[seg_keep(world.reflectors)],
        ParkingSlots(p.xy[k], p.yaw[k], p.long_term[k], p.lt_len[k], p.lt_wid[k], p.lt_flip[k]),
        world.buildings,
        world.bounds,
    )


def path_street(
    world: StaticWorld, path_xy: np.ndarray, seed: int, keep_clear_m: float = 3.5
) -> StaticWorld:
    """``world`` with a street that follows ``path_xy`` (:func:`street_polyline`), cleared of
    what stood there and lined as the city's own streets are: facades, street furniture and
    parking slots on both sides, so a drive along a given trajectory passes the near,
    repeatable structure a drive along the city's own streets does. Nothing is left within
    ``keep_clear_m`` of the path (the inside of tight turns)."""
    from scipy.spatial import cKDTree

    cfg = world.config
    rng = np.random.default_rng([seed, 111])
    pts, s = street_polyline(path_xy, step_m=15.0)
    off = cfg.facade_offset_m
    world = carve_corridor(world, [street_polyline(path_xy, step_m=1.0)[0]], off - 1.0)
    b = _CityBuilder(cfg, rng, world.network)
    slots_xy, slots_yaw = [], []
    # Cross streets one block apart, as on the city's own streets: open views down them.
    cross = np.cumsum(rng.uniform(cfg.block_min_m, cfg.block_max_m, int(s[-1] - s[0]) // 50 + 2))
    cross = s[0] + cross - rng.uniform(0.0, cfg.block_max_m)
    for k, (a, c) in enumerate(itertools.pairwise(pts)):
        if np.min(np.abs(cross - 0.5 * (s[k] + s[k + 1]))) < off:
            continue
        d = _unit(c - a)
        for right in (-_left(d), _left(d)):
            b.facade_row(a + right * off, c + right * off, -right)
            b.street_side(a - d * (off + 2.5), c + d * (off + 2.5), right, rail=False)
            if rng.uniform() < cfg.parking_edge_fraction:
                length = float(np.linalg.norm(c - a))
                sl = np.arange(0.5 * cfg.parking_slot_m, length, cfg.parking_slot_m)
                slots_xy.append(a + sl[:, None] * d + right * 4.7)
                slots_yaw.append(np.full(len(sl), float(np.arctan2(d[1], d[0]))))
    tree = cKDTree(np.vstack([path_xy, pts]))
    sc = Scatterers.concat(b.parts)
    sc = sc.subset(tree.query(sc.xy)[0] > keep_clear_m) if len(sc) else sc
    occ = np.array(b.occluders, dtype=np.float64).reshape(-1, 4)
    if len(occ):
        mid = 0.5 * (occ[:, :2] + occ[:, 2:])
        occ = occ[(tree.query(occ[:, :2])[0] > keep_clear_m) & (tree.query(mid)[0] > keep_clear_m)]
    sxy = np.concatenate(slots_xy) if slots_xy else np.zeros((0, 2))
    syaw = np.concatenate(slots_yaw) if slots_yaw else np.zeros(0)
    ok = tree.query(sxy)[0] > keep_clear_m if len(sxy) else np.zeros(0, bool)
    sxy, syaw = sxy[ok], syaw[ok]
    n = len(sxy)
    p = world.parking
    parking = ParkingSlots(
        np.vstack([p.xy, sxy]),
        np.concatenate([p.yaw, syaw]),
        np.concatenate([p.long_term, rng.uniform(0, 1, n) < cfg.long_term_parked_fraction]),
        np.concatenate([p.lt_len, rng.uniform(4.2, 5.3, n)]),
        np.concatenate([p.lt_wid, rng.uniform(1.75, 2.0, n)]),
        np.concatenate([p.lt_flip, rng.uniform(0, 1, n) < 0.15]),
    )
    return StaticWorld(
        cfg,
        world.network,
        Scatterers.concat([world.scatterers, sc]),
        np.vstack([world.occluders, occ]),
        np.vstack([world.reflectors, occ]),
        parking,
        world.buildings + b.buildings,
        world.bounds,
    )
