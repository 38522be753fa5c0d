"""CLI commands of the nuScenes stage (light at import time: the reader is imported on call)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer


def scene_names(text: str | None, option: str = "--scenes") -> list[str] | None:
    """The names of a comma-separated ``--scenes`` value; ``None`` when the option was not given.

    An empty name (``--scenes ""``, ``a,,b``, a trailing comma) is a :class:`ConfigError`: the
    option left out means all scenes, an empty value is a mistake, not a request for them."""
    from radarslam.errors import ConfigError

    if text is None:
        return None
    names = [s.strip() for s in text.split(",")]
    if not all(names):
        raise ConfigError(
            f"{option} {text!r}: empty scene name; give comma-separated scene names, or leave "
            f"{option} out for all scenes"
        )
    return names


def stats(
    dataroot: Annotated[Path, typer.Argument(help="nuScenes dataroot (holds <version>/*.json).")],
    version: Annotated[str, typer.Option(help="v1.0-mini, v1.0-trainval or v1.0-test.")] = (
        "v1.0-mini"
    ),
    scenes: Annotated[
        str | None, typer.Option(help="Comma-separated scene names (default: all).")
    ] = None,
    max_sweeps: Annotated[
        int | None, typer.Option(help="Read at most N sweeps per radar and scene.", min=1)
    ] = None,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Also write the statistics to this JSON file.")
    ] = None,
) -> None:
    """Radar statistics of a dataroot beside the figures measured on real nuScenes."""
    from radarslam.io.atomic import write_text_atomic
    from radarslam.nuscenes.reader import NuScenesRadar
    from radarslam.nuscenes.stats import dataset_statistics

    names = scene_names(scenes)
    reader = NuScenesRadar(dataroot, version)
    if names:
        for name in names:
            reader.scene(name)  # unknown names fail before any work
    st = dataset_statistics(reader, scenes=names, max_sweeps_per_scene=max_sweeps)
    typer.echo(st.to_markdown())
    if json_out is not None:
        write_text_atomic(json_out, st.to_json() + "\n")
        typer.echo(f"wrote {json_out}")
