"""Generate a synthetic dataroot in the exact nuScenes layout.

Order of writing: radar .pcd files and per-log sidecars first (workers, one log each), then the
tables, then ``synthetic/summary.json``. A run that was interrupted therefore lacks tables or the
summary and is detected by :func:`is_complete`.

This module is the driver; planning the logs is in :mod:`.planning` and simulating one log in
:mod:`.one_log`.
"""

from __future__ import annotations

import os
import shutil
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from radarslam.config import dump_config
from radarslam.errors import ConfigError
from radarslam.io.atomic import write_json_atomic, write_text_atomic
from radarslam.sim.config import SimConfig, load_sim_config
from radarslam.sim.one_log import _run_log, simulate_log
from radarslam.sim.planning import LogPlan, _cached_world, _world_for, plan_logs
from radarslam.sim.radar import NUSCENES_MOUNTS, mounting_errors
from radarslam.sim.world import drivable_mask
from radarslam.sim.writer import make_token, static_tables, write_map

CHANNELS = tuple(m.channel for m in NUSCENES_MOUNTS)
TABLES = (
    "attribute",
    "calibrated_sensor",
    "category",
    "ego_pose",
    "instance",
    "log",
    "map",
    "sample",
    "sample_annotation",
    "sample_data",
    "scene",
    "sensor",
    "visibility",
)

# callers and tests import these from here
__all__ = [
    "CHANNELS",
    "TABLES",
    "LogPlan",
    "SimulationSummary",
    "_world_for",
    "is_complete",
    "plan_logs",
    "simulate",
    "simulate_log",
]


@dataclass
class SimulationSummary:
    dataroot: str
    version: str
    preset: str
    seed: int
    n_logs: int
    n_days: int
    n_scenes: int
    n_samples: int
    n_sweeps: int
    n_points: int
    bytes_written: int
    seconds: float
    per_log: list[dict] = field(default_factory=list)
    # The simulated vehicle's true deviations from the written calibration, per channel.
    mounting_yaw_error_deg: dict[str, float] = field(default_factory=dict)
    timestamp_offset_s: dict[str, float] = field(default_factory=dict)

    @property
    def sweeps_per_s(self) -> float:
        return self.n_sweeps / max(self.seconds, 1e-9)

    def describe(self) -> str:
        """One line for the user: what was written, where, how fast."""
        return (
            f"wrote {self.dataroot} ({self.version}): {self.n_logs} logs on {self.n_days} days, "
            f"{self.n_scenes} scenes, {self.n_samples} key frames, {self.n_sweeps} radar sweeps, "
            f"{self.n_points} points, {self.bytes_written / 1e6:.1f} MB in {self.seconds:.1f} s "
            f"({self.sweeps_per_s:.0f} sweeps/s)"
        )


def is_complete(dataroot: str | Path, version: str) -> bool:
    """True when a generation run finished (its summary is written after every table)."""
    root = Path(dataroot)
    return (root / "synthetic" / "summary.json").is_file() and all(
        (root / version / f"{t}.json").is_file() for t in TABLES
    )


def simulate(
    config_or_preset: SimConfig | str | Path,
    out_dir: str | Path,
    seed: int | None = None,
    progress: bool = True,
    overrides: list[str] | None = None,
    jobs: int | None = None,
    overwrite: bool = False,
    trajectory_tum: str | Path | None = None,
) -> SimulationSummary:
    """Generate a nuScenes-layout dataroot in ``out_dir``; deterministic for a seed."""
    t_start = time.perf_counter()
    if isinstance(config_or_preset, SimConfig):
        cfg = config_or_preset
        if overrides:
            from radarslam.config import apply_overrides, build_config

            cfg = build_config(SimConfig, apply_overrides(cfg.model_dump(mode="json"), overrides))
    else:
        cfg = load_sim_config(config_or_preset, overrides)
    upd = {}
    if seed is not None:
        upd["seed"] = int(seed)
    if jobs is not None:
        upd["jobs"] = int(jobs)
    if upd:  # validated like the config's own values (a negative seed is refused)
        from radarslam.config import build_config

        cfg = build_config(SimConfig, {**cfg.model_dump(), **upd}, source="simulate arguments")
    if trajectory_tum is not None:
        cfg = cfg.model_copy(
            update={"ego": cfg.ego.model_copy(update={"trajectory_tum": str(trajectory_tum)})}
        )
    for w in cfg.scenario.missing_radar:
        if w.channel not in CHANNELS:
            raise ConfigError(
                f"scenario.missing_radar: unknown channel {w.channel!r} "
                f"(one of {', '.join(CHANNELS)})"
            )
    world, tum = _cached_world(cfg)
    duration = None
    if tum is not None:
        duration = float(tum[-1, 0] - tum[0, 0])
        if duration < 3.0:
            raise ConfigError(
                f"{cfg.ego.trajectory_tum}: trajectory lasts {duration:.1f} s; need >= 3 s"
            )
    plans = plan_logs(cfg, duration)
    root = Path(out_dir)
    version = cfg.output.version
    if root.exists() and not root.is_dir():
        raise ConfigError(f"{root}: output path exists and is not a directory")
    existing = [
        p for p in (version, "samples", "sweeps", "synthetic", "maps") if (root / p).exists()
    ]
    if existing:
        if not overwrite:
            raise ConfigError(
                f"{root}: already holds a dataroot ({', '.join(existing)}); "
                "pass --overwrite to replace it"
            )
        for p in existing:  # tables first, so an interrupted overwrite is detectable
            shutil.rmtree(root / p)
    for ch in CHANNELS:
        (root / "samples" / ch).mkdir(parents=True, exist_ok=True)
        (root / "sweeps" / ch).mkdir(parents=True, exist_ok=True)

    results = _run_all(cfg, plans, root, progress)

    tables: dict[str, list] = {t: [] for t in TABLES}
    tables.update(static_tables(cfg.seed, CHANNELS))
    for res in results:
        tables["log"].append(res["log"])
        for name in ("calibrated_sensor", "scene", "sample", "sample_data", "ego_pose"):
            tables[name].extend(res[name])
    map_tok = make_token(cfg.seed, "map", 0)
    img = drivable_mask(world, cfg.city.map_resolution_m)
    fname = write_map(root, map_tok, img)
    tables["map"] = [
        {
            "token": map_tok,
            "log_tokens": [p.token for p in plans],
            "category": "semantic_prior",
            "filename": fname,
        }
    ]
    # Sidecar: the world model (ground truth for tests; the reader never needs it).
    syn = root / "synthetic"
    syn.mkdir(parents=True, exist_ok=True)
    write_text_atomic(syn / "config.yaml", dump_config(cfg))
    sc = world.scatterers
    tmp = syn / ".world.tmp.npz"
    np.savez_compressed(
        tmp,
        scatterer_xy=sc.xy,
        scatterer_class=sc.cls,
        scatterer_rcs_dbsm=sc.rcs_dbsm,
        occluders=world.occluders,
        reflectors=world.reflectors,
        nodes=world.network.nodes,
        edges=world.network.edges,
        parking_xy=world.parking.xy,
        map_resolution_m=cfg.city.map_resolution_m,
    )
    os.replace(tmp, syn / "world.npz")
    (root / version).mkdir(parents=True, exist_ok=True)
    for name in TABLES:
        path = root / version / f"{name}.json"
        write_json_atomic(path, tables[name], indent=None)
        os.chmod(path, 0o644)  # readable like the radar files (the temp file was 0600)
    stats = [r["stats"] for r in results]
    errors = mounting_errors(cfg.radar, cfg.seed)
    summary = SimulationSummary(
        dataroot=str(root),
        version=version,
        preset=cfg.name,
        seed=cfg.seed,
        n_logs=len(plans),
        n_days=len({p.day for p in plans}),
        n_scenes=len(tables["scene"]),
        n_samples=len(tables["sample"]),
        n_sweeps=len(tables["sample_data"]),
        n_points=sum(s["points"] for s in stats),
        bytes_written=_du(root),
        seconds=time.perf_counter() - t_start,
        per_log=stats,
        mounting_yaw_error_deg={ch: e.yaw_deg for ch, e in errors.items()},
        timestamp_offset_s={ch: e.timestamp_offset_s for ch, e in errors.items()},
    )
    write_json_atomic(syn / "summary.json", asdict(summary))
    return summary


def _du(root: Path) -> int:
    total = 0
    for dirpath, _, files in os.walk(root):
        for f in files:
            total += os.path.getsize(os.path.join(dirpath, f))
    return total


def _run_all(cfg: SimConfig, plans: list[LogPlan], root: Path, progress: bool) -> list[dict]:
    from tqdm import tqdm

    jobs = min(cfg.jobs, len(plans))
    bar = tqdm(total=len(plans), desc=f"simulate {cfg.name}", unit="log", disable=not progress)
    results: list[dict] = []
    try:
        if jobs <= 1:
            for p in plans:
                results.append(simulate_log(cfg, p, str(root)))
                bar.update(1)
        else:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            ctx = mp.get_context("fork") if "fork" in mp.get_all_start_methods() else None
            args = [(cfg.model_dump_json(), p, str(root)) for p in plans]
            with ProcessPoolExecutor(jobs, mp_context=ctx) as ex:
                for res in ex.map(_run_log, args):
                    results.append(res)
                    bar.update(1)
    finally:
        bar.close()
    return results
