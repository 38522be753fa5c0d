"""CLI command of the odometry stage (light at import time: the pipeline is imported on call)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

DEFAULT_CONFIG = Path(__file__).resolve().parents[1] / "configs" / "odometry" / "default.yaml"


def odometry(
    dataroot: Annotated[Path, typer.Option(help="nuScenes dataroot (holds <version>/*.json).")],
    out: Annotated[Path, typer.Option(help="Output folder (new, or an earlier run's: replaced).")],
    version: Annotated[str, typer.Option(help="v1.0-mini, v1.0-trainval or v1.0-test.")] = (
        "v1.0-mini"
    ),
    scenes: Annotated[
        str | None, typer.Option(help="Comma-separated scene names (default: all).")
    ] = None,
    config: Annotated[
        Path | None,
        typer.Option(help="Odometry YAML (default: radarslam/configs/odometry/default.yaml)."),
    ] = None,
    set_: Annotated[
        list[str] | None,
        typer.Option("--set", help="Config override key.sub=value (repeatable)."),
    ] = None,
    method: Annotated[
        str, typer.Option(help="ours, doppler (dead reckoning) or kiss-icp (plain pipeline).")
    ] = "ours",
    progress: Annotated[bool, typer.Option(help="Show a progress bar.")] = True,
) -> None:
    """Radar odometry over scenes: a results folder (docs/outputs.md) with the poses in TUM and
    KITTI formats, ground truth alongside; `radarslam eval OUT` evaluates it."""
    from radarslam.config import load_config
    from radarslam.errors import ConfigError
    from radarslam.io.results import check_results_dir
    from radarslam.nuscenes.commands import check_output_names, scene_names
    from radarslam.nuscenes.reader import NuScenesRadar
    from radarslam.odometry.baselines import METHODS
    from radarslam.odometry.config import OdometryConfig
    from radarslam.odometry.run import run_odometry, write_outputs

    if method not in METHODS:
        raise ConfigError(f"--method {method!r}: choose one of {', '.join(METHODS)}")
    path = config if config is not None else (DEFAULT_CONFIG if DEFAULT_CONFIG.is_file() else None)
    cfg = load_config(OdometryConfig, path, set_)
    check_results_dir(out)  # a bad --out fails now, not after the run
    reader = NuScenesRadar(dataroot, version)
    names = scene_names(scenes)
    infos = [reader.scene(n) for n in names] if names else reader.scenes()
    check_output_names(reader, infos)
    traj = run_odometry(reader, infos, cfg, method=method, progress=progress)
    summary = write_outputs(traj, out, cfg)
    tot = summary["total"]

    def fmt(v, spec):
        return "n/a" if v is None else format(v, spec)

    drift = "n/a (no 100 m stretch)" if tot["drift_pct"] is None else f"{tot['drift_pct']:.2f} %"
    typer.echo(
        f"{method}: {tot['frames']} frames, {tot['path_length_m']:.0f} m, "
        f"ATE {fmt(tot['ate_rmse_m'], '.2f')} m, drift per 100 m {drift}, "
        f"{tot['mean_ms_per_frame']:.1f} ms/frame -> {out}"
    )
    rigs = summary.get("doppler_calibration_by_rig") or [summary.get("doppler_calibration")]
    for cal in rigs:
        line = calibration_line(cal)
        if line:
            typer.echo(line)


def calibration_line(cal: dict | None) -> str | None:
    """One line of a rig's Doppler calibration as ``summary.json`` holds it, or None."""
    if not cal or not cal.get("mounting_yaw_error_deg"):
        return None
    yaws = cal["mounting_yaw_error_deg"]
    sigmas = cal.get("mounting_yaw_sigma_deg") or {}
    parts = [
        f"{ch.removeprefix('RADAR_')} {v:+.2f}" + (f" +- {sigmas[ch]:.2f}" if ch in sigmas else "")
        for ch, v in yaws.items()
    ]
    scenes = ", ".join(cal.get("scenes") or [])
    scale = f"radar speed scale error {cal.get('radar_speed_scale_error', 0.0):+.3f} (configured"
    if cal.get("speed_scale_sigma"):  # estimated on top of the configured one
        scale += f"; {cal['speed_scale_error']:+.4f} +- {cal['speed_scale_sigma']:.4f} left"
    return (
        f"Doppler calibration{f' ({scenes})' if scenes else ''}: mounting yaw error (deg) "
        f"{'; '.join(parts)}; {scale})"
    )
