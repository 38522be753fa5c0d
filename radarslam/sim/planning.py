"""Planning a synthetic dataset: the world of a config, and each log's day, route and scenes."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from radarslam.errors import ConfigError
from radarslam.sim.config import SimConfig
from radarslam.sim.ego import read_tum
from radarslam.sim.world import StaticWorld, build_world, path_street
from radarslam.sim.writer import add_days, log_start, make_token


@dataclass
class LogPlan:
    index: int
    token: str
    name: str
    date: str
    day: int
    start_us: int
    route_index: int
    reversed: bool
    ego_speed_mps: float
    scene_windows: list[tuple[float, float]]
    first_scene_number: int = 1  # scene names run scene-0001, scene-0002, ... over all logs


def _world_for(cfg: SimConfig) -> tuple[StaticWorld, np.ndarray | None]:
    tum = read_tum(cfg.ego.trajectory_tum) if cfg.ego.trajectory_tum else None
    city = cfg.city
    if tum is not None:
        # Build the city around the given trajectory, then clear a corridor along it.
        lo, hi = tum[:, 1:3].min(0), tum[:, 1:3].max(0)
        mean_block = 0.5 * (city.block_min_m + city.block_max_m)
        nbx = int(np.clip(np.ceil((hi[0] - lo[0] + 300) / mean_block), 2, 60))
        nby = int(np.clip(np.ceil((hi[1] - lo[1] + 300) / mean_block), 2, 60))
        city = city.model_copy(
            update={
                "n_blocks_x": nbx,
                "n_blocks_y": nby,
                "origin_m": (float(lo[0] - 150), float(lo[1] - 150)),
            }
        )
    world = build_world(city, cfg.seed, cfg.traffic.light_cycle_s)
    if tum is not None:
        # The grid's streets do not follow the path: line the path itself with a street like
        # the city's own, cleared of the grid's buildings.
        world = path_street(world, tum[:, 1:3], cfg.seed)
    return world, tum


def plan_logs(cfg: SimConfig, duration_s: float | None = None) -> list[LogPlan]:
    sch = cfg.schedule
    rng = np.random.default_rng([cfg.seed, 303])
    if sch.n_logs <= sch.n_days:
        days = np.sort(rng.choice(sch.n_days, sch.n_logs, replace=False))
    else:
        days = np.sort(rng.integers(0, sch.n_days, sch.n_logs))
    plans = []
    for i in range(sch.n_logs):
        date = add_days(sch.start_date, int(days[i]))
        start_us, name = log_start(date, float(rng.uniform(8 * 3600, 18 * 3600)))
        route_index = i % sch.n_routes
        reverse = bool(rng.uniform() < sch.reverse_fraction)
        if i == 1 and sch.reverse_fraction > 0 and sch.n_routes == 1:
            reverse = True  # two logs on one route: one drives it the other way round
        if i == sch.n_routes and sch.reverse_fraction > 0:
            reverse = True  # the first revisit of route 0 is in the opposite direction
        start = float(rng.uniform(0.5, 3.0))  # drawn either way: later draws stay the same
        # A given trajectory is covered from its start (its first pose is the scene's).
        windows, t = [], (0.1 if duration_s is not None else start)
        for _ in range(sch.scenes_per_log):
            end = t + sch.scene_duration_s
            if duration_s is not None and end > duration_s - 0.2:
                end = min(end, duration_s - 0.2)
                if end - t >= min(2.0, sch.scene_duration_s):
                    windows.append((t, end))
                break
            windows.append((t, end))
            t = end + float(rng.uniform(*sch.scene_gap_s))
        if not windows:
            raise ConfigError(
                f"trajectory of {duration_s:.1f} s is too short for one scene; need >= 3 s"
            )
        plans.append(
            LogPlan(
                i,
                make_token(cfg.seed, "log", i),
                name,
                date,
                int(days[i]),
                start_us,
                route_index,
                reverse,
                float(rng.uniform(*cfg.ego.desired_speed_mps)),
                windows,
            )
        )
    number = 1
    for p in plans:
        p.first_scene_number = number
        number += len(p.scene_windows)
    return plans


_WORLD_CACHE: dict[str, tuple[StaticWorld, np.ndarray | None]] = {}


def _cached_world(cfg: SimConfig):
    key = cfg.model_dump_json()
    if key not in _WORLD_CACHE:
        _WORLD_CACHE.clear()
        _WORLD_CACHE[key] = _world_for(cfg)
    return _WORLD_CACHE[key]
