"""Generator speed per preset: seconds, sweeps/s, MB written (printed as a table).

    python bench/simulate.py                      # tiny and demo
    python bench/simulate.py --presets city --jobs 2 --set schedule.n_logs=6   # bounded city

The peer run is the same preset with ``--jobs 1`` when ``--jobs`` > 1 (speed-up column).
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path


def run(preset: str, jobs: int | None, overrides: list[str]) -> dict:
    from radarslam.sim import simulate

    tmp = Path(tempfile.mkdtemp(prefix=f"bench_sim_{preset}_"))
    try:
        cpu0 = time.process_time()
        s = simulate(preset, tmp / "root", progress=False, overrides=overrides, jobs=jobs)
        cpu = time.process_time() - cpu0
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    if jobs is None:
        from radarslam.sim.config import load_sim_config

        jobs = load_sim_config(preset, overrides).jobs
    return {
        "preset": preset, "jobs": min(jobs, s.n_logs), "logs": s.n_logs, "scenes": s.n_scenes,
        "key frames": s.n_samples, "sweeps": s.n_sweeps, "points": s.n_points,
        "seconds": s.seconds, "parent cpu s": cpu, "sweeps/s": s.sweeps_per_s,
        "ms/sweep": 1000 * s.seconds / max(s.n_sweeps, 1), "MB": s.bytes_written / 1e6,
    }  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--presets", nargs="+", default=["tiny", "demo"])
    ap.add_argument("--jobs", type=int, default=None)
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    args = ap.parse_args()
    rows = []
    for preset in args.presets:
        row = run(preset, args.jobs, args.overrides)
        if args.jobs and args.jobs > 1 and row["logs"] > 1:
            peer = run(preset, 1, args.overrides)
            rows.append(peer)
            row["speed-up vs 1 job"] = peer["seconds"] / row["seconds"]
        rows.append(row)
    cols = list(dict.fromkeys(k for r in rows for k in r))
    fmt = {float: "{:.2f}", int: "{:d}", str: "{}"}
    cells = [[fmt[type(r.get(c, ""))].format(r.get(c, "")) if c in r else "" for c in cols]
             for r in rows]  # fmt: skip
    width = [max(len(c), *(len(x[i]) for x in cells)) for i, c in enumerate(cols)]
    print(" | ".join(c.rjust(w) for c, w in zip(cols, width, strict=True)))
    print("-+-".join("-" * w for w in width))
    for x in cells:
        print(" | ".join(v.rjust(w) for v, w in zip(x, width, strict=True)))


if __name__ == "__main__":
    main()
