"""Matched-paths realism benchmark: each real scene against a synthetic twin driven along its path.

    python bench/realism.py              # all 5 scenes of ../shared/data/nuscenes-mini-radar
    python bench/realism.py --scenes scene-0061 --json /tmp/realism.json
    python bench/realism.py --preset demo --set radar.clutter_rate=0.5 --regenerate
    python bench/realism.py --twin-mounting estimated   # each twin gets the real car's mounting

Per real scene:

1. Its ground-truth ego path (the radar frames' poses, as ``radarslam odometry`` writes
   ``gt_<scene>.tum``) is exported to ``WORK/<scene>/gt_<scene>.tum``.
2. A synthetic twin is simulated along that path (``radarslam.sim.simulate`` with
   ``trajectory_tum``; preset ``--preset``, one log of one scene as long as the real scene, the
   ``--set`` overrides, a seed derived from ``--seed`` and the scene name; with
   ``--twin-mounting estimated`` the radars' mounting yaw errors are the ones ours estimated on
   the real scene instead of the simulator's draw) into
   ``WORK/<scene>/twin_<digest>``. The digest covers the path, the resolved simulator config,
   the seed and the simulator's sources, so a complete twin is reused unless ``--regenerate``.
   The simulator starts a scene 0.5-3 s into the drive and ends it 0.2 s before the path's end,
   so the twin covers less than the real scene; the window it covers is printed.
3. The three odometry methods of bench/odometry.py (Doppler dead reckoning, the kiss-icp peer,
   ours) run on the real scene and on its twin through bench/odometry.py's own functions.

Printed:

* Per method, per scene and pooled: real ATE, twin ATE and their ratio (ATE after SE(2)
  alignment, pooled over scenes as bench/odometry.py pools it: RMS weighted by frames).
  Verdicts: each method's pooled twin ATE within 0.5-2x of its real ATE, and the same ranking
  of the three methods by pooled ATE on real and twin.
* The radar statistics of the real scenes and of the twins side by side (the table of
  ``radarslam stats TWIN --reference REAL``: ``radarslam.nuscenes.stats``, every twin scene read
  as one dataset). Verdict per statistic: ratio twin / real within 0.8-1.25, except re-detection
  fractions (absolute difference within 0.08) and RCS levels in dBsm (difference within 1.5 dB;
  a ratio of decibels means nothing). A figure without a ratio (nothing to measure, or a real
  value of 0 against a non-zero twin) is n/a and does not pass.

The real data is read from where it lies (CC BY-NC-SA; never copied into the repository).
"""

from __future__ import annotations

import argparse
import hashlib
import math
import multiprocessing as mp
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from _cli import sibling_bench

odobench = sibling_bench("odometry")
METHODS: tuple[str, ...] = odobench.METHODS

ATE_RATIO_RANGE = (0.5, 2.0)
STAT_RATIO_RANGE = (0.8, 1.25)
REDETECT_ABS_TOL = 0.08
RCS_DB_TOL = 1.5
#: Overrides that make a twin one log of one scene (its duration is appended per scene).
TWIN_OVERRIDES = ("schedule.n_logs=1", "schedule.scenes_per_log=1")


def scene_seed(seed: int, scene: str) -> int:
    """The twin's simulator seed: fixed per (``--seed``, scene), whatever scenes are selected."""
    return int(hashlib.md5(f"{seed}:{scene}".encode()).hexdigest()[:8], 16) % (2**31)


def run_all(jobs_list: list[tuple], jobs: int, desc: str) -> list[dict]:
    """``odobench.run_segment`` over the jobs, in order, on up to ``jobs`` processes."""
    from tqdm import tqdm

    n = max(1, min(jobs, len(jobs_list)))
    with tqdm(total=len(jobs_list), desc=desc, unit="scene") as bar:
        if n == 1:
            out = []
            for job in jobs_list:
                out.append(odobench.run_segment(job))
                bar.update(1)
            return out
        with mp.get_context("fork").Pool(n) as pool:
            out = []
            for res in pool.imap(odobench.run_segment, jobs_list, chunksize=1):
                out.append(res)
                bar.update(1)
            return out


def export_gt(work: Path, scene: str, result: dict) -> Path:
    """``WORK/<scene>/gt_<scene>.tum`` (and .kitti) of the real run's ground truth, written by the
    results folder's own writer."""
    from radarslam.io.results import trajectory_path, write_trajectories

    folder = work / scene
    folder.mkdir(parents=True, exist_ok=True)
    write_trajectories(folder, scene, result["t"], {"gt": result["gt"]})
    return trajectory_path(folder, "gt", scene)


def car_overrides(result: dict) -> list[str]:
    """The simulator override that gives a twin the mounting yaw errors ours estimated on the real
    scene (its Doppler calibration pass and run together), so the twin drives the same car."""
    est = (result.get("calibration") or {}).get("mounting_yaw_error_deg") or {}
    if not est:
        return []
    body = ", ".join(f"{ch}: {float(v)!r}" for ch, v in sorted(est.items()))
    return [f"radar.mounting_yaw_error_deg={{{body}}}"]


def make_twin(
    work: Path,
    scene: str,
    gt_tum: Path,
    duration_s: float,
    preset: str,
    user_overrides: list[str],
    seed: int,
    regenerate: bool,
) -> tuple[Path, str, list[str]]:
    """(dataroot, version, overrides) of the scene's twin, generated unless a complete one with
    the same inputs exists."""
    import radarslam.sim as sim_pkg
    from radarslam.sim import simulate
    from radarslam.sim.config import load_sim_config
    from radarslam.sim.generate import is_complete

    # The user's --set last, so that they win over the twin's schedule.
    overrides = [*TWIN_OVERRIDES, f"schedule.scene_duration_s={duration_s!r}", *user_overrides]
    cfg = load_sim_config(preset, overrides)
    # The simulator's sources are part of the key: a twin made by older code is not reused.
    sources = sorted(Path(sim_pkg.__file__).parent.glob("*.py"))
    key = "|".join(
        [gt_tum.read_text(), cfg.model_dump_json(), str(seed)] + [p.read_text() for p in sources]
    )
    root = work / scene / f"twin_{hashlib.md5(key.encode()).hexdigest()[:10]}"
    version = cfg.output.version
    if regenerate or not is_complete(root, version):
        print(f"simulating the twin of {scene} (seed {seed}) -> {root}", flush=True)
        simulate(
            preset,
            root,
            seed=seed,
            progress=True,
            overrides=overrides,
            jobs=1,
            overwrite=True,
            trajectory_tum=gt_tum,
        )
    else:
        print(f"reusing the twin of {scene}: {root}", flush=True)
    return root, version, overrides


def drive_start_us(twin_root: Path) -> int:
    """Time 0 of the twin's drive (the first pose of the path), from the generator's sidecar."""
    logs = sorted((twin_root / "synthetic" / "logs").glob("*.npz"))
    with np.load(logs[0]) as z:
        return int(z["gt_time_us"][0])


def sweep_counts(reader, scene: str) -> dict[str, int]:
    from radarslam.types import RADAR_CHANNELS

    return {ch: len(reader.sweep_tokens(scene, ch)) for ch in RADAR_CHANNELS}


def twin_dataset_statistics(twins: dict[str, tuple[Path, str]], work: Path):
    """The statistics of every twin scene as one dataset, by the code of ``radarslam stats``."""
    from tqdm import tqdm

    from radarslam.nuscenes.reader import NuScenesRadar
    from radarslam.nuscenes.stats import odometry_inputs, read_scene, statistics_of

    point_filter, estimator = odometry_inputs()
    records = []
    for scene, (root, version) in tqdm(twins.items(), desc="stats twins", unit="scene"):
        reader = NuScenesRadar(root, version)
        rec = read_scene(reader, reader.scenes()[0], point_filter, estimator)
        # Every twin's scene is scene-0001; the Doppler drive figures are keyed by scene name.
        records.append(replace(rec, name=f"twin-{scene}"))
    versions = sorted({v for _, v in twins.values()})
    return statistics_of(records, f"{len(twins)} twin(s) under {work}", ",".join(versions))


def stat_verdict(row: dict) -> tuple[str, str]:
    """(PASS / FAIL / n/a, criterion with the measured gap) of one row of the stats comparison."""
    v, r, ratio, kind = row["value"], row["reference"], row["ratio"], row["kind"]
    if row["key"].startswith(("redetect", "radar_redetect")):
        if v is None or r is None:
            return "n/a", f"|twin - real| <= {REDETECT_ABS_TOL}"
        d = v - r
        ok = abs(d) <= REDETECT_ABS_TOL
        return ("PASS" if ok else "FAIL"), f"difference {d:+.3f} (|.| <= {REDETECT_ABS_TOL})"
    if kind == "dB":
        if ratio is None:
            return "n/a", f"|twin - real| <= {RCS_DB_TOL} dB"
        ok = abs(ratio) <= RCS_DB_TOL
        return ("PASS" if ok else "FAIL"), f"difference {ratio:+.1f} dB (|.| <= {RCS_DB_TOL} dB)"
    lo, hi = STAT_RATIO_RANGE
    if ratio is None:
        return "n/a", f"ratio in {lo}-{hi}"
    ok = lo <= ratio <= hi
    return ("PASS" if ok else "FAIL"), f"ratio {ratio:.2f} (in {lo}-{hi})"


def _plain(x: Any) -> Any:
    """JSON types: numpy scalars and arrays converted, NaN and inf as null."""
    if isinstance(x, dict):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    return x


def print_matching(rows: dict[str, dict]) -> None:
    print("\nMatched paths (times since the path's first pose; sweeps F/FL/FR/BL/BR)")
    head = (
        f"{'scene':<12} {'real s':>6} {'twin window s':>13} {'twin s':>6} {'real m':>6} "
        f"{'twin m':>6} {'frames':>9} {'sweeps real':>23} {'sweeps twin':>23}"
    )
    print(head)
    print("-" * len(head))
    for scene, x in rows.items():
        a, b = x["twin_window_s"]
        print(
            f"{scene:<12} {x['real_duration_s']:>6.1f} {a:>6.1f}-{b:<6.1f} "
            f"{x['twin_duration_s']:>6.1f} {x['real_length_m']:>6.0f} {x['twin_length_m']:>6.0f} "
            f"{x['real_frames']:>4d}/{x['twin_frames']:<4d} "
            f"{'/'.join(str(n) for n in x['real_sweeps'].values()):>23} "
            f"{'/'.join(str(n) for n in x['twin_sweeps'].values()):>23}"
        )


def print_ate_tables(
    real: dict[str, dict[str, dict]],
    twin: dict[str, dict[str, dict]],
    pool_real: dict[str, dict],
    pool_twin: dict[str, dict],
) -> None:
    for method in METHODS:
        print(
            f"\n{method}: ATE (m, SE(2)-aligned), and scale (ground-truth length over the "
            "estimate's, similarity alignment; pooled weighted by length)"
        )
        head = (
            f"{'scene':<12} {'real':>8} {'twin':>8} {'twin/real':>9} {'scale real':>11} "
            f"{'scale twin':>11}"
        )
        print(head)
        print("-" * len(head))
        for scene, a, b in [
            *((s, real[s][method], twin[s][method]) for s in real),
            ("pooled", pool_real[method], pool_twin[method]),
        ]:
            ratio = b["ate_m"] / a["ate_m"] if a["ate_m"] > 0 else float("nan")
            print(
                f"{scene:<12} {a['ate_m']:>8.3f} {b['ate_m']:>8.3f} {ratio:>9.2f} "
                f"{a['sim2_scale']:>11.4f} {b['sim2_scale']:>11.4f}"
            )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--dataroot", type=Path, default=odobench.REAL_DATAROOT)
    ap.add_argument("--version", default="v1.0-mini")
    ap.add_argument("--scenes", default=None, help="comma-separated scene names (default: all)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/radarslam_bench_realism"))
    ap.add_argument("--preset", default="demo", help="the twins' simulator preset")
    ap.add_argument(
        "--set",
        action="append",
        default=[],
        help="simulator config override for every twin, e.g. radar.clutter_rate=0.5",
    )
    ap.add_argument("--seed", type=int, default=0, help="base of the per-scene twin seeds")
    ap.add_argument(
        "--twin-mounting",
        choices=("drawn", "estimated"),
        default="drawn",
        help="the twins' radar mounting yaw errors: drawn from the simulator's mixture (its "
        "seed), or the ones ours estimates on the real scene (the twin of that car)",
    )
    ap.add_argument("--regenerate", action="store_true", help="simulate the twins again")
    ap.add_argument("--jobs", type=int, default=1, help="odometry runs in parallel")
    ap.add_argument("--json", type=Path, default=None, help="write every number to this file")
    args = ap.parse_args()
    t_start = time.perf_counter()

    from radarslam.nuscenes.commands import comparison, comparison_markdown
    from radarslam.nuscenes.reader import NuScenesRadar
    from radarslam.nuscenes.stats import dataset_statistics
    from radarslam.sim.config import load_sim_config

    load_sim_config(args.preset, args.set)  # a bad --set is one line now, not after the real runs
    if not (args.dataroot / args.version).is_dir():
        print(
            f"error: {args.dataroot / args.version}: no such folder (the real nuScenes radar split "
            "lives in ../shared/data/nuscenes-mini-radar; pass --dataroot/--version)",
            file=sys.stderr,
        )
        sys.exit(2)
    reader = NuScenesRadar(args.dataroot, args.version)
    known = [s.name for s in reader.scenes()]
    scenes = [s for s in args.scenes.split(",") if s] if args.scenes else known
    unknown = [s for s in scenes if s not in known]
    if unknown or not scenes:
        print(
            f"error: --scenes: {', '.join(unknown) or 'none given'} not in {args.dataroot} "
            f"({', '.join(known)})",
            file=sys.stderr,
        )
        sys.exit(2)
    args.work.mkdir(parents=True, exist_ok=True)

    real_results = run_all(
        [(str(args.dataroot), args.version, [s], []) for s in scenes], args.jobs, "odometry real"
    )
    twins: dict[str, tuple[Path, str]] = {}
    info: dict[str, dict] = {}
    for scene, r in zip(scenes, real_results, strict=True):
        duration = float((r["t"][-1] - r["t"][0]) * 1e-6)
        gt_tum = export_gt(args.work, scene, r)
        seed = scene_seed(args.seed, scene)
        car = car_overrides(r) if args.twin_mounting == "estimated" else []
        root, version, overrides = make_twin(
            args.work, scene, gt_tum, duration, args.preset, [*car, *args.set], seed,
            args.regenerate,
        )  # fmt: skip
        twins[scene] = (root, version)
        info[scene] = {
            "gt_tum": str(gt_tum),
            "twin_dataroot": str(root),
            "twin_version": version,
            "twin_seed": seed,
            "twin_overrides": overrides,
        }
    twin_scene = {}
    for scene, (root, version) in twins.items():
        names = [s.name for s in NuScenesRadar(root, version).scenes()]
        if len(names) != 1:
            raise SystemExit(f"error: twin {root} holds {len(names)} scenes, expected 1")
        twin_scene[scene] = names[0]
    twin_results = run_all(
        [(str(twins[s][0]), twins[s][1], [twin_scene[s]], []) for s in scenes],
        args.jobs,
        "odometry twins",
    )

    real = {s: {m: odobench.segment_metrics(r, m) for m in METHODS} for s, r in
            zip(scenes, real_results, strict=True)}  # fmt: skip
    twin = {s: {m: odobench.segment_metrics(r, m) for m in METHODS} for s, r in
            zip(scenes, twin_results, strict=True)}  # fmt: skip
    pool_real = {m: odobench.pooled([real[s][m] for s in scenes]) for m in METHODS}
    pool_twin = {m: odobench.pooled([twin[s][m] for s in scenes]) for m in METHODS}

    matching = {}
    for scene, rr, tr in zip(scenes, real_results, twin_results, strict=True):
        t0 = drive_start_us(twins[scene][0])
        twin_reader = NuScenesRadar(*twins[scene])
        matching[scene] = {
            "real_duration_s": float((rr["t"][-1] - rr["t"][0]) * 1e-6),
            "twin_window_s": [float((tr["t"][0] - t0) * 1e-6), float((tr["t"][-1] - t0) * 1e-6)],
            "twin_duration_s": float((tr["t"][-1] - tr["t"][0]) * 1e-6),
            "real_length_m": real[scene]["doppler"]["length_m"],
            "twin_length_m": twin[scene]["doppler"]["length_m"],
            "real_frames": len(rr["t"]),
            "twin_frames": len(tr["t"]),
            "real_sweeps": sweep_counts(reader, scene),
            "twin_sweeps": sweep_counts(twin_reader, twin_scene[scene]),
        }
    print(f"\nreal: {args.dataroot} ({args.version}); twins: preset {args.preset}, {args.work}")
    print_matching(matching)
    print_ate_tables(real, twin, pool_real, pool_twin)

    verdicts = []

    def say(ok: bool, text: str) -> None:
        verdicts.append(f"{'PASS' if ok else 'FAIL'}  {text}")

    lo, hi = ATE_RATIO_RANGE
    ate_ratio = {}
    for m in METHODS:
        a, b = pool_real[m]["ate_m"], pool_twin[m]["ate_m"]
        ate_ratio[m] = b / a if a > 0 else float("nan")
        say(
            lo <= ate_ratio[m] <= hi,
            f"{m}: pooled twin ATE {b:.3f} m = {ate_ratio[m]:.2f}x real {a:.3f} m "
            f"(target {lo}-{hi}x)",
        )
    rank_real = sorted(METHODS, key=lambda m: pool_real[m]["ate_m"])
    rank_twin = sorted(METHODS, key=lambda m: pool_twin[m]["ate_m"])
    say(
        rank_real == rank_twin,
        f"same ranking of methods by pooled ATE: real {' < '.join(rank_real)}, "
        f"twin {' < '.join(rank_twin)}",
    )
    print("\n" + "\n".join(verdicts))

    real_stats = dataset_statistics(reader, scenes, desc="stats real")
    twin_stats = twin_dataset_statistics(twins, args.work)
    rows = comparison(twin_stats.to_dict(), real_stats.to_dict())
    print("\nRadar statistics: twins (dataroot) against the real scenes (reference)\n")
    print(comparison_markdown(rows, twin_stats, real_stats))
    for row in rows:
        row["verdict"], row["criterion"] = stat_verdict(row)
    passed = sum(row["verdict"] == "PASS" for row in rows)
    print("Verdict per statistic (twin against real):")
    for row in rows:
        print(f"  {row['verdict']:<4}  {row['label']}: {row['criterion']}")
    n_na = sum(row["verdict"] == "n/a" for row in rows)
    stats_line = f"radar statistics: {passed} of {len(rows)} pass" + (
        f" ({n_na} n/a)" if n_na else ""
    )
    print(stats_line)
    runtime = time.perf_counter() - t_start
    print(f"\nruntime {runtime:.0f} s")

    if args.json:
        from radarslam.io.atomic import write_json_atomic

        summary = {
            "dataroot": str(args.dataroot),
            "version": args.version,
            "preset": args.preset,
            "seed": args.seed,
            "twin_mounting": args.twin_mounting,
            "sim_overrides": args.set,
            "scenes": {
                s: {
                    **info[s],
                    **matching[s],
                    "real": {m: odobench._public(real[s][m]) for m in METHODS},
                    "twin": {m: odobench._public(twin[s][m]) for m in METHODS},
                }
                for s in scenes
            },
            "pooled": {"real": pool_real, "twin": pool_twin},
            "ate_ratio_twin_over_real": ate_ratio,
            "ranking": {"real": rank_real, "twin": rank_twin, "same": rank_real == rank_twin},
            "verdicts": verdicts,
            "stats": {
                "real": real_stats.to_dict(),
                "twin": twin_stats.to_dict(),
                "comparison": rows,
                "passed": passed,
                "total": len(rows),
                "summary": stats_line,
            },
            "runtime_s": runtime,
        }
        # write_json_atomic: a temporary file beside the target, then os.replace.
        write_json_atomic(args.json, _plain(summary))
        print(f"wrote {args.json}")


if __name__ == "__main__":
    from _cli import guarded

    guarded(main)
