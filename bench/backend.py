"""Back-end benchmark: iSAM2 update time per key frame while a multi-lap pose graph grows to
N nodes with loop closures, then the final batch LM (warm from iSAM2) and a cold batch LM (from
dead reckoning) as the in-process peer.

    python bench/backend.py [--nodes 10000] [--poses-per-lap 500] [--loop-every 25]
"""

from __future__ import annotations

import argparse

import numpy as np
from rich.console import Console
from rich.table import Table

from radarslam.eval.metrics import ate
from radarslam.io.loops import NodeKey
from radarslam.slam.pose_graph import PoseGraph, PoseGraphConfig
from radarslam.slam.synthetic_graph import grow_isam2


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--nodes", type=int, default=10_000)
    ap.add_argument("--poses-per-lap", type=int, default=500)
    ap.add_argument("--loop-every", type=int, default=25)
    ap.add_argument("--robust", choices=["cauchy", "huber", "none"], default="cauchy")
    ap.add_argument("--false-loops", type=float, default=0.0, help="fraction of injected outliers")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()

    grown = grow_isam2(
        args.nodes,
        args.poses_per_lap,
        args.loop_every,
        args.robust,
        args.false_loops,
        args.seed,
        progress=True,
    )
    pg, sg, n, loops_at = grown.graph, grown.synthetic, grown.num_nodes, grown.loops_at
    num_loops, isam_total_s = grown.num_loops, grown.total_s
    step_ms, loop_step = grown.update_ms, grown.with_loop
    gt = sg.gt[:n]
    ate_isam = ate(pg.session_poses("s"), gt, align="none").rmse_m
    pg.optimize_batch()
    warm_s, warm_it = pg.last_batch_time_s, pg.last_batch_iterations
    ate_batch = ate(pg.session_poses("s"), gt, align="none").rmse_m

    # peer: the same graph solved by batch LM only, from dead reckoning
    cold = PoseGraph(PoseGraphConfig(loop_robust=args.robust, incremental=False))
    cold.add_session("s", sg.gt[0], anchor="prior")
    for k in range(n - 1):
        cold.add_odometry("s", k, k + 1, sg.odometry[k], sg.odometry_covariance)
        for lp in loops_at.get(k + 1, []):
            cold.add_loop(NodeKey("s", lp.i), NodeKey("s", lp.j), lp.i_from_j, sg.loop_information)
    cold.optimize_batch()
    cold_s, cold_it = cold.last_batch_time_s, cold.last_batch_iterations
    ate_cold = ate(cold.session_poses("s"), gt, align="none").rmse_m
    ate_dr = ate(sg.dead_reckoning[:n], gt, align="none").rmse_m

    st = np.asarray(step_ms)
    ls = np.asarray(loop_step)
    con = Console(width=140)
    t = Table(title=f"pose-graph back end: {n} nodes, {num_loops} loops ({args.robust})")
    columns = ("stage", "median ms", "p99 ms", "max ms", "total s", "LM iters", "ATE m")
    columns += ("vs cold LM",)
    for c in columns:
        t.add_column(c, justify="left" if c == "stage" else "right")

    def row(name, arr, total, iters, err):
        t.add_row(
            name,
            f"{np.median(arr):.3f}" if arr is not None and len(arr) else "-",
            f"{np.percentile(arr, 99):.3f}" if arr is not None and len(arr) else "-",
            f"{np.max(arr):.2f}" if arr is not None and len(arr) else "-",
            f"{total:.2f}",
            str(iters) if iters is not None else "-",
            f"{err:.3f}",
            f"{total / cold_s:.2f}x",
        )

    row("iSAM2 update, all key frames", st, isam_total_s, None, ate_isam)
    row("  key frames without loop", st[~ls], float(st[~ls].sum()) / 1e3, None, ate_isam)
    row("  key frames with a loop", st[ls], float(st[ls].sum()) / 1e3, None, ate_isam)
    row("batch LM warm (from iSAM2)", None, warm_s, warm_it, ate_batch)
    row("batch LM cold (dead reckoning)", None, cold_s, cold_it, ate_cold)
    con.print(t)
    con.print(f"dead-reckoning ATE {ate_dr:.3f} m")


if __name__ == "__main__":
    from _cli import guarded

    guarded(main)
