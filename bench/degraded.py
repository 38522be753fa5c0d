"""Odometry on degraded real radar: sweeps lost at random, one radar silent, all radars silent.

    python bench/degraded.py            # the real split, ../shared/data/nuscenes-mini-radar
    python bench/degraded.py --dataroot D --version v1.0-trainval [--scenes a,b]
    python bench/degraded.py ... --json results.json
    python bench/degraded.py --only silent --set fusion.calibration.pass_frame_stride=1

Real ARS408 sweeps can be empty (2.4 % of the sweeps of real nuScenes scenes other than these five)
and a radar can fail or be blocked. Each condition is a copy of the dataroot under ``--work``
(links to the real files, the tables unchanged) in which the chosen sweeps are rewritten as valid
radar files with no point; the three methods of ``bench/odometry.py`` then run on it exactly as on
the real split (each scene its own segment, started on its ground truth):

* ``clean``: the dataroot as it is;
* ``empty 2.4 %`` / ``empty 10 %``: every sweep emptied with that probability (``--seed``);
* ``silent RADAR_X``: every sweep of one radar empty (each radar in turn);
* ``only RADAR_FRONT``: every other radar silent (a single forward radar, whose Doppler alone
  cannot observe the yaw rate);
* ``silent all 1 s``: all five radars empty for 1 s in the middle of each scene (frames still
  come, with no point: the odometry holds its last motion through them);
* ``RADAR_X off 3 deg``: one radar's written extrinsic (``calibrated_sensor.json``) turned by
  3 deg about its vertical axis, each radar in turn: a unit knocked out of line, which every
  method reads as the truth (the real split's own mounting errors are about 1 deg).

Per condition: pooled ATE (SE(2)-aligned) of each method, ours against the peer, and the scene
where ours is worst against the clean run. The real data is read in place and linked, never copied
into the repository.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from _cli import sibling_bench

from radarslam.types import RADAR_CHANNELS

odobench = sibling_bench("odometry")
METHODS: tuple[str, ...] = odobench.METHODS
#: Rate of empty sweeps on real nuScenes scenes other than the shared five.
REAL_EMPTY_RATE = 0.024
OUTAGE_S = 1.0
#: Mounting-yaw error of a radar knocked out of line.
TURN_DEG = 3.0


def conditions(channels: list[str]) -> list[tuple[str, dict]]:
    out: list[tuple[str, dict]] = [("clean", {})]
    out += [(f"empty {100 * p:g} %", {"empty_rate": p}) for p in (REAL_EMPTY_RATE, 0.10)]
    out += [(f"silent {ch}", {"silent": ch}) for ch in channels]
    out += [(f"only {ch}", {"only": ch}) for ch in ("RADAR_FRONT",) if ch in channels]
    out.append((f"silent all {OUTAGE_S:g} s", {"outage_s": OUTAGE_S}))
    out += [(f"{ch} off {TURN_DEG:g} deg", {"turned": ch}) for ch in channels]
    return out


@dataclass(frozen=True)
class Sweep:
    filename: str  # relative to the dataroot
    channel: str
    timestamp_us: int


def sweeps_of(reader, scene: str) -> list[Sweep]:
    """Every radar sweep of a scene (no file is read)."""
    return [
        Sweep(filename, channel, t_us)
        for channel in RADAR_CHANNELS
        for filename, t_us in reader.sweep_files(scene, channel)
    ]


def emptied(sweeps: list[Sweep], spec: dict, rng: np.random.Generator) -> set[str]:
    """Files of one scene's sweeps that a condition empties."""
    if "empty_rate" in spec:
        return {s.filename for s in sweeps if rng.random() < spec["empty_rate"]}
    if "silent" in spec:
        return {s.filename for s in sweeps if s.channel == spec["silent"]}
    if "only" in spec:
        return {s.filename for s in sweeps if s.channel != spec["only"]}
    if "outage_s" in spec:
        t = np.array([s.timestamp_us for s in sweeps])
        mid, half = 0.5 * (t.min() + t.max()), 0.5 * spec["outage_s"] * 1e6
        return {s.filename for s in sweeps if abs(s.timestamp_us - mid) <= half}
    return set()


def degraded_root(
    src: Path, dst: Path, empty: set[str], turned: str | None = None, version: str = ""
) -> None:
    """``dst``: ``src`` with the files in ``empty`` replaced by radar files with no point and, with
    ``turned``, ``version``/calibrated_sensor.json rewritten with that channel's extrinsics turned
    by :data:`TURN_DEG`; every other file a link to the original."""
    from radarslam.nuscenes.pcd import pcd_bytes
    from radarslam.types import RADAR_DTYPE

    if dst.exists():
        shutil.rmtree(dst)
    blank = pcd_bytes(np.zeros(0, dtype=RADAR_DTYPE), padding=1)
    for dirpath, _, files in os.walk(src):
        rel = Path(dirpath).relative_to(src)
        (dst / rel).mkdir(parents=True, exist_ok=True)
        for f in files:
            key = (rel / f).as_posix()
            if key in empty:
                (dst / rel / f).write_bytes(blank)
            else:
                os.symlink(Path(dirpath, f).resolve(), dst / rel / f)
    if turned is not None:
        path = dst / version / "calibrated_sensor.json"
        records = turned_extrinsics(src / version, turned, TURN_DEG)
        path.unlink()
        path.write_text(json.dumps(records))


def turned_extrinsics(tables: Path, channel: str, yaw_deg: float) -> list[dict]:
    """``tables``/calibrated_sensor.json with every record of ``channel``'s sensors turned by
    ``yaw_deg`` about the sensor's z axis, as a mounting error turns it
    (:func:`~radarslam.odometry.calibration.mounting_rotations`: ``mounting_yaw_deg`` undoes it)."""
    from radarslam.geometry import quat_to_rotation, rotation_to_quat
    from radarslam.odometry.calibration import mounting_rotations

    sensors = json.loads((tables / "sensor.json").read_text())
    tokens = {r["token"] for r in sensors if r["channel"] == channel}
    records = json.loads((tables / "calibrated_sensor.json").read_text())
    turn = mounting_rotations({channel: yaw_deg})[channel][:3, :3]
    for r in records:
        if r["sensor_token"] in tokens:
            turned = quat_to_rotation(r["rotation"]) @ turn
            r["rotation"] = [float(v) for v in rotation_to_quat(turned)]
    return records


def run_condition(
    root: Path, version: str, scenes: list[str], jobs: int, overrides: list[str] | None = None
) -> dict:
    jobs_list = [(str(root), version, [s], list(overrides or [])) for s in scenes]
    with mp.get_context("fork").Pool(max(1, min(jobs, len(jobs_list)))) as pool:
        results = pool.map(odobench.run_segment, jobs_list, chunksize=1)
    per_scene = {
        r["scenes"][0]: {m: odobench.segment_metrics(r, m) for m in METHODS} for r in results
    }
    pool_rows = {m: odobench.pooled([rows[m] for rows in per_scene.values()]) for m in METHODS}
    return {
        "scenes": {s: {m: rows[m]["ate_m"] for m in METHODS} for s, rows in per_scene.items()},
        "pooled": {m: pool_rows[m]["ate_m"] for m in METHODS},
        "mounting_yaw_error_deg": {
            r["scenes"][0]: r["calibration"].get("mounting_yaw_error_deg", {}) for r in results
        },
    }


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dataroot", type=Path, default=odobench.REAL_DATAROOT)
    ap.add_argument("--version", default="v1.0-mini")
    ap.add_argument("--scenes", default=None, help="comma-separated scene names (default: all)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/radarslam_bench_degraded"))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0, help="which sweeps are emptied at random")
    ap.add_argument(
        "--only", default=None, help="run only the conditions whose name contains this (and clean)"
    )
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="odometry config override, as in bench/odometry.py (repeatable)",
    )
    args = ap.parse_args()

    from radarslam.io.atomic import write_text_atomic
    from radarslam.nuscenes.reader import NuScenesRadar

    if not (args.dataroot / args.version).is_dir():
        print(
            f"error: {args.dataroot / args.version}: no such folder (the real nuScenes radar "
            "split lives in ../shared/data/nuscenes-mini-radar; see its README)",
            file=sys.stderr,
        )
        return 2
    # A bad dataroot or scene name is a RadarSlamError: one line from guarded().
    odobench.odometry_config(args.set)  # a bad --set fails here, in one line
    reader = NuScenesRadar(args.dataroot, args.version)
    scenes = args.scenes.split(",") if args.scenes else [s.name for s in reader.scenes()]
    for s in scenes:
        reader.scene(s)  # an unknown name fails here, before any copy is made
    sweeps = {s: sweeps_of(reader, s) for s in scenes}
    channels = sorted({w.channel for s in scenes for w in sweeps[s]})
    rows: dict[str, dict] = {}
    for k, (name, spec) in enumerate(conditions(channels)):
        if args.only and name != "clean" and args.only not in name:
            continue
        rng = np.random.default_rng(args.seed)
        empty = set().union(*(emptied(sweeps[s], spec, rng) for s in scenes))
        root = args.dataroot
        if empty or "turned" in spec:
            root = args.work / f"condition{k}"
            degraded_root(args.dataroot.resolve(), root, empty, spec.get("turned"), args.version)
        if "turned" in spec:
            print(f"{name}: {spec['turned']}'s extrinsic turned", flush=True)
        else:
            print(f"{name}: {len(empty)} sweeps emptied", flush=True)
        rows[name] = run_condition(root, args.version, scenes, args.jobs, args.set)
        rows[name]["sweeps_emptied"] = len(empty)
        if "turned" in spec:
            ch = spec["turned"]
            est = [row.get(ch, np.nan) for row in rows[name]["mounting_yaw_error_deg"].values()]
            clean_est = [
                row.get(ch, np.nan) for row in rows["clean"]["mounting_yaw_error_deg"].values()
            ]
            print(
                f"  {ch}'s mounting-yaw error as ours estimates it per scene, deg: "
                + " ".join(f"{e:+.2f}" for e in est)
                + " (clean: " + " ".join(f"{e:+.2f}" for e in clean_est) + ")",
                flush=True,
            )  # fmt: skip
    clean = rows["clean"]["scenes"]
    print(f"\npooled ATE (SE(2)-aligned), m, over {len(scenes)} scenes")
    head = f"{'condition':<26}" + "".join(f"{m:>10}" for m in METHODS)
    print(head + f"{'ours/peer':>11}  ours' worst scene against clean")
    print("-" * (len(head) + 46))
    for name, row in rows.items():
        p = row["pooled"]
        worst = max(scenes, key=lambda s: row["scenes"][s]["ours"] - clean[s]["ours"])
        w = row["scenes"][worst]
        print(
            f"{name:<26}" + "".join(f"{p[m]:>10.3f}" for m in METHODS)
            + f"{p['ours'] / p['kiss-icp']:>11.2f}  {worst} {clean[worst]['ours']:.3f} -> "
            f"{w['ours']:.3f} (peer {w['kiss-icp']:.3f})"
        )  # fmt: skip
    if args.json:
        write_text_atomic(args.json, json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    from _cli import guarded

    guarded(main)
