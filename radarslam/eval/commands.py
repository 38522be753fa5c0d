"""CLI command ``radarslam eval`` (light at import time: numpy work happens on call)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def _fmt(v, digits: int = 3) -> str:
    if v is None:
        return "-"
    if isinstance(v, float):
        return "-" if v != v else f"{v:.{digits}f}"
    return str(v)


def eval_command(
    results_dir: Annotated[
        Path, typer.Argument(help="Results folder of run or odometry (docs/outputs.md).")
    ],
    config: Annotated[
        Path | None,
        typer.Option(help="Evaluation YAML (default: radarslam/configs/eval/default.yaml)."),
    ] = None,
    override: Annotated[
        list[str] | None, typer.Option("--set", help="Config override key.sub=value (repeatable).")
    ] = None,
    plots: Annotated[bool, typer.Option(help="Write PNG plots under RESULTS_DIR/plots.")] = True,
) -> None:
    """ATE / RPE / drift of odometry and SLAM side by side, loop precision/recall (a folder of
    `radarslam odometry`: its odometry only); writes RESULTS_DIR/metrics.json."""
    from radarslam.config import CONFIG_DIR, load_config
    from radarslam.eval.evaluate import EvalConfig, evaluate_results
    from radarslam.io.atomic import atomic_batch

    path = config
    if path is None and (CONFIG_DIR / "eval" / "default.yaml").is_file():
        path = CONFIG_DIR / "eval" / "default.yaml"
    cfg = load_config(EvalConfig, path, list(override or []))
    cfg.plots = plots
    with atomic_batch():  # metrics.json and the plots replace the previous ones together
        report = evaluate_results(results_dir, cfg)
    print_report(report, results_dir, cfg)


def print_report(report, results_dir: Path, cfg) -> None:
    """Rich tables of an :class:`~radarslam.eval.evaluate.EvalReport`."""
    from rich.console import Console
    from rich.table import Table

    console = Console()
    groups = [
        (
            "trajectory error",
            [
                ("poses", "num_poses", 0),
                ("path m", "path_length_m", 1),
                ("ATE m SE2", "ate_rmse_m", 3),
                ("ATE m first", "ate_first_rmse_m", 3),
                ("drift %", "drift_pct", 2),
            ],
        ),
        (
            "ATE along / across the ground truth's heading, and at the clock offset that fits "
            "best (estimate early: +)",
            [
                ("along m", "ate_along_m", 3),
                ("across m", "ate_cross_m", 3),
                ("clock offset ms", "clock_offset_ms", 0),
                ("ATE m there", "ate_at_clock_offset_m", 3),
            ],
        ),
        (
            "scale of a similarity alignment (ground truth / estimate: above 1, the estimate is "
            f"short; where the truth drives {cfg.scale_min_path_m:g} m or more) and the ATE it "
            "leaves; turn scale (estimate's heading change / ground "
            f"truth's, step by step: above 1, it turns too far; where the truth turns "
            f"{cfg.turn_scale_min_deg:g} deg or more)",
            [
                ("scale", "sim2_scale", 4),
                ("ATE m Sim2", "ate_sim2_m", 3),
                ("turned deg", "turned_deg", 0),
                ("turn scale", "turn_scale", 4),
            ],
        ),
        (
            "relative pose error (RMSE)",
            [
                (f"RPE {cfg.rpe_time_s:g}s m", "rpe_time_trans_rmse_m", 3),
                (f"RPE {cfg.rpe_time_s:g}s deg", "rpe_time_rot_rmse_deg", 3),
                (f"RPE {cfg.rpe_distance_m:g}m m", "rpe_dist_trans_rmse_m", 3),
                (f"RPE {cfg.rpe_distance_m:g}m deg", "rpe_dist_rot_rmse_deg", 3),
            ],
        ),
    ]
    for title, cols in groups:
        table = Table(title=f"{title}: {results_dir.name}")
        table.add_column("session")
        table.add_column("run")
        for name, _, _ in cols:
            table.add_column(name, justify="right")
        for s in report.sessions:
            for kind, m in report.per_session[s].items():
                d = m.as_dict()
                table.add_row(s, kind, *[_fmt(d[key], digits) for _, key, digits in cols])
        console.print(table)
    if report.run:
        run = Table(title="whole run (per-session errors pooled; joint = one alignment)")
        for name in (
            "run", "sessions", "poses", "ATE m (SE2)", "ATE m (first)", "ATE m (joint)",
            "turn scale",
        ):  # fmt: skip
            run.add_column(name, justify="left" if name == "run" else "right")
        for kind, d in report.run.items():
            run.add_row(kind, str(d["num_sessions"]), str(d["num_poses"]), _fmt(d["ate_rmse_m"]),
                        _fmt(d["ate_first_rmse_m"]), _fmt(d["ate_joint_rmse_m"]),
                        _fmt(d["turn_scale"], 4))  # fmt: skip
        console.print(run)
        comps = {kind: d.get("components_joint") or [] for kind, d in report.run.items()}
        if max(len(c) for c in comps.values()) > 1:
            table = Table(title="map components of several sessions, each aligned on its own")
            for name in ("component", "sessions", *(f"ATE m (joint) {k}" for k in comps)):
                table.add_column(name, justify="right")
            by_index = {k: {c["component"]: c for c in cs} for k, cs in comps.items()}
            for index in sorted({i for cs in by_index.values() for i in cs}):
                found = [cs[index] for cs in by_index.values() if index in cs]
                cells = [
                    _fmt(cs[index]["ate_joint_rmse_m"]) if index in cs else "-"
                    for cs in by_index.values()
                ]
                table.add_row(str(index), str(len(found[0]["sessions"])), *cells)
            console.print(table)
    if report.loops is not None:
        lm = report.loops.as_dict()
        console.print(
            f"loops: {lm['num_candidates']} candidates, {lm['num_accepted']} accepted, "
            f"{lm['num_correct']} correct; precision {_fmt(lm['precision'])}, recall "
            f"{_fmt(lm['recall'])} ({lm['num_recalled_queries']}/{lm['num_revisit_queries']} "
            "GT revisit queries)"
        )
    console.print(f"wrote {Path(results_dir) / 'metrics.json'}")
