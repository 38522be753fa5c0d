"""CLI commands ``radarslam run`` and ``radarslam demo`` (light at import time)."""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Annotated

import typer

from radarslam.nuscenes.commands import SCENES_HELP, VERSION_DEFAULT


class Dataset(str, Enum):
    nuscenes = "nuscenes"
    synthetic = "synthetic"


#: Named SLAM presets, radarslam/configs/slam/<name>.yaml (one for real radar and the synthetic
#: world alike).
SLAM_PRESETS = ("default",)


def _slam_config(
    config: Path | None,
    overrides: list[str] | None,
    no_loops: bool,
    checkpoint,
    preset: str = "default",
):
    """The SLAM config: ``config`` (a YAML path, or a preset name), else the ``preset``."""
    from radarslam.config import CONFIG_DIR, load_config
    from radarslam.slam.config import SlamConfig

    if config is not None and str(config) in SLAM_PRESETS and not config.exists():
        preset, config = str(config), None
    path = config if config is not None else CONFIG_DIR / "slam" / f"{preset}.yaml"
    overrides = list(overrides or [])
    if no_loops:
        overrides.append("loops.enabled=false")
    if checkpoint is not None:
        overrides.append(f"loops.checkpoint={checkpoint}")
    return load_config(SlamConfig, path, overrides)


def _check_selection(scenes: str | None, location: str | None) -> list[str] | None:
    """The ``--scenes`` names; a :class:`ConfigError` for an empty name or for ``--scenes``
    together with ``--location`` (one would be ignored)."""
    from radarslam.errors import ConfigError
    from radarslam.nuscenes.commands import scene_names

    names = scene_names(scenes)
    if names is not None and location is not None:
        raise ConfigError(f"--scenes {scenes!r} and --location {location!r}: give one or the other")
    return names


def _select_scenes(reader, scenes: str | None, location: str | None, max_scenes: int | None):
    from radarslam.errors import ConfigError, DataError

    names = _check_selection(scenes, location)
    if names is not None:
        chosen = [reader.scene(s) for s in names]
    elif location:
        chosen = reader.scenes_for_location(location)
    else:
        locations = reader.locations()
        if len(locations) > 1:
            raise DataError(
                f"{reader.dataroot}: scenes of several locations ({', '.join(locations)}); "
                "choose --location or --scenes"
            )
        chosen = reader.scenes_for_location(locations[0]) if locations else []
    if max_scenes is not None:
        if max_scenes < 1:
            raise ConfigError(f"--max-scenes {max_scenes}: must be at least 1")
        chosen = chosen[:max_scenes]
    if not chosen:
        raise DataError(f"{reader.dataroot}: no scene selected")
    return chosen


def run_slam(
    dataroot: Path,
    version: str,
    out: Path,
    scenes: str | None = None,
    location: str | None = None,
    max_scenes: int | None = None,
    config=None,
    evaluate: bool = True,
    progress: bool = True,
):
    """Run SLAM on a nuScenes-layout dataroot and write the results folder (then evaluate)."""
    import time

    from rich.console import Console

    from radarslam.config import dump_config
    from radarslam.nuscenes.commands import check_output_names
    from radarslam.nuscenes.reader import NuScenesRadar
    from radarslam.slam.config import SlamConfig
    from radarslam.slam.outputs import check_results_dir, write_results
    from radarslam.slam.pipeline import SlamPipeline

    console = Console(stderr=True)
    config = config or SlamConfig()
    check_results_dir(out)  # a bad --out fails now, not after the run
    reader = NuScenesRadar(dataroot, version)
    infos = _select_scenes(reader, scenes, location, max_scenes)
    check_output_names(reader, infos)
    console.print(
        f"SLAM on {len(infos)} scene(s) of {dataroot} ({version}): "
        + ", ".join(i.name for i in infos[:8])
        + (" ..." if len(infos) > 8 else "")
    )
    t0 = time.perf_counter()
    pipeline = SlamPipeline(reader, config, progress=progress)
    result = pipeline.run(infos)
    wall_s = time.perf_counter() - t0
    t = result.timings
    timing = {
        "wall_s": wall_s,
        "sensor_duration_s": result.duration_s,
        "real_time_factor": result.duration_s / wall_s if wall_s > 0 else None,
        "frames": t.frames,
        "key_frames": t.key_frames,
        "stages_s": {
            "data": t.data_s,
            "odometry": t.odometry_s,
            "key_frames": t.key_frame_s,
            "place_recognition": t.place_recognition_s,
            "verification": t.verification_s,
            "backend_isam2": t.backend_s,
            "final_optimization": t.final_optimization_s,
            "calibration_pass": t.calibration_pass_s,
        },
        "components": [
            {"sessions": list(c.sessions), "anchored": c.anchored} for c in result.components
        ],
        "loops": {"candidates": len(result.loops), "accepted": len(result.accepted_loops)},
    }
    console.print(
        f"{t.frames} frames, {t.key_frames} key frames, {len(result.accepted_loops)} loops "
        f"accepted of {len(result.loops)} verified, {len(result.components)} map component(s); "
        f"{result.duration_s:.0f} s of radar in {wall_s:.1f} s "
        f"({timing['real_time_factor']:.1f}x real time)"
    )
    if result.continues:
        drives = len(infos) - len(result.continues)
        console.print(
            f"{len(result.continues)} scene(s) continue the scene before them (same log, "
            f"back to back): {drives} drive(s)"
        )
    from radarslam.odometry.commands import calibration_line

    # One line per radar rig (a run over two cars' scenes estimates two calibrations), with the
    # scenes it was estimated on, as `radarslam odometry` prints them.
    for cal in result.doppler_calibrations_by_rig or [result.doppler_calibration or {}]:
        line = calibration_line(cal)
        if line:
            console.print(line, soft_wrap=True)
    reports = []
    finish = None
    if evaluate:
        from radarslam.config import CONFIG_DIR, load_config
        from radarslam.eval.evaluate import EvalConfig, evaluate_results

        eval_cfg = load_config(EvalConfig, CONFIG_DIR / "eval" / "default.yaml")

        def finish(folder: Path) -> None:  # metrics and plots join the folder before it is out
            reports.append(evaluate_results(folder, eval_cfg, name=out))

    write_results(
        out,
        result.sessions,
        result.loops,
        result.static_map,
        config_yaml=dump_config(config),
        components=[c.sessions for c in result.components],  # the anchored map first
        extra_json={"timing.json": timing, **_summary(result)},
        finish=finish,
        continues=result.continues,
    )
    if reports:
        from radarslam.eval.commands import print_report

        print_report(reports[0], out, eval_cfg)
    return result


def _summary(result) -> dict[str, dict]:
    """``summary.json`` of a SLAM folder: the odometry's Doppler calibration, as in an odometry
    folder's (none when the odometry estimates no calibration)."""
    cal = result.doppler_calibration
    if not cal:
        return {}
    summary: dict = {"doppler_calibration": cal}
    if result.doppler_calibrations_by_rig:
        summary["doppler_calibration_by_rig"] = result.doppler_calibrations_by_rig
    return {"summary.json": summary}


def run_command(
    ctx: typer.Context,
    out: Annotated[Path, typer.Option("--out", help="Results folder (created).")],
    dataset: Annotated[Dataset, typer.Option(help="Real nuScenes or the synthetic world.")] = (
        Dataset.nuscenes
    ),
    dataroot: Annotated[
        Path | None,
        typer.Option(help="nuScenes dataroot; for --dataset synthetic: where it is generated."),
    ] = None,
    version: Annotated[
        str,
        typer.Option(
            help="v1.0-mini, v1.0-trainval or v1.0-test; with --dataset synthetic, the preset's."
        ),
    ] = VERSION_DEFAULT,
    preset: Annotated[str, typer.Option(help="Synthetic preset (tiny, demo, city).")] = "demo",
    scenes: Annotated[str | None, typer.Option(help=SCENES_HELP)] = None,
    location: Annotated[
        str | None, typer.Option(help="All scenes of one location, oldest first (multi-session).")
    ] = None,
    max_scenes: Annotated[
        int | None, typer.Option(min=1, help="Use only the first N scenes.")
    ] = None,
    config: Annotated[
        Path | None,
        typer.Option(help="SLAM YAML, or a preset name (default; radarslam/configs/slam/)."),
    ] = None,
    override: Annotated[
        list[str] | None, typer.Option("--set", help="Config override key.sub=value (repeatable).")
    ] = None,
    no_loops: Annotated[bool, typer.Option("--no-loops", help="Odometry only.")] = False,
    checkpoint: Annotated[
        Path | None, typer.Option(help="AutoPlace checkpoint (default: the shipped compact one).")
    ] = None,
    evaluate: Annotated[bool, typer.Option(help="Evaluate against ground truth.")] = True,
    progress: Annotated[bool, typer.Option(help="Show progress bars.")] = True,
) -> None:
    """SLAM over one or several scenes (one map, one session per scene) -> results folder."""
    from radarslam.errors import DataError
    from radarslam.slam.outputs import check_results_dir

    cfg = _slam_config(
        config,
        override,
        no_loops,
        checkpoint,
        preset="default",
    )
    _check_selection(scenes, location)
    check_results_dir(out)  # before generating or reading any data
    if dataset == Dataset.synthetic:
        dataroot = dataroot or Path("data") / f"synthetic-{preset}"
        # the preset sets the version it generates; a --version given names a copy made earlier
        if getattr(ctx.get_parameter_source("version"), "name", "DEFAULT") == "DEFAULT":
            version = ensure_synthetic(preset, dataroot, progress)
    elif dataroot is None:
        raise DataError("--dataroot is required with --dataset nuscenes")
    run_slam(
        dataroot,
        version,
        out,
        scenes,
        location,
        max_scenes,
        cfg,
        evaluate=evaluate,
        progress=progress,
    )


def ensure_synthetic(preset: str, dataroot: Path, progress: bool) -> str:
    """Generate the preset into ``dataroot`` unless a complete copy is there; its version."""
    from radarslam.sim.config import load_sim_config
    from radarslam.sim.generate import is_complete, simulate

    version = load_sim_config(preset).output.version
    if not is_complete(dataroot, version):
        summary = simulate(preset, dataroot, progress=progress)
        typer.echo(summary.describe(), err=True)
    return version


def demo_command(
    out: Annotated[Path, typer.Option("--out", help="Folder for the data and the results.")] = (
        Path("runs/demo")
    ),
    preset: Annotated[str, typer.Option(help="Synthetic preset.")] = "demo",
    override: Annotated[
        list[str] | None, typer.Option("--set", help="SLAM config override key.sub=value.")
    ] = None,
    progress: Annotated[bool, typer.Option(help="Show progress bars.")] = True,
) -> None:
    """Generate the synthetic demo city, run multi-session SLAM on it, evaluate and plot."""
    from radarslam.sim.config import load_sim_config
    from radarslam.slam.outputs import check_results_dir

    dataroot = out / "data"
    cfg = _slam_config(None, override, False, None, preset="default")
    load_sim_config(preset)  # a bad preset fails before any folder is made
    results = out / "results"
    check_results_dir(results)  # before generating the data
    version = ensure_synthetic(preset, dataroot, progress)
    run_slam(dataroot, version, results, config=cfg, progress=progress)
    typer.echo(
        f"results in {results}: trajectories (TUM/KITTI), loops.csv, metrics.json, map.ply, "
        f"plots/*.png",
        err=True,
    )
