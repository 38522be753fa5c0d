"""``radarslam simulate``: light at import (the generator is imported inside the command)."""

from __future__ import annotations

from pathlib import Path

import typer

from radarslam.errors import ConfigError


def simulate_command(
    preset: str = typer.Option("demo", "--preset", help="tiny, demo, city, or a YAML path"),
    out: Path = typer.Option(..., "--out", help="dataroot to write (nuScenes layout)"),
    seed: int | None = typer.Option(None, "--seed", help="random seed (default: the preset's)"),
    trajectory: Path | None = typer.Option(
        None, "--trajectory", help="drive along this TUM file (t x y z qx qy qz qw)"
    ),
    set_: list[str] = typer.Option([], "--set", help="config override key.sub=value (repeatable)"),
    jobs: int | None = typer.Option(None, "--jobs", help="worker processes (one log each)"),
    overwrite: bool = typer.Option(False, "--overwrite", help="replace an existing dataroot"),
    quiet: bool = typer.Option(False, "--quiet", help="no progress bar"),
) -> None:
    """Generate a synthetic city dataset in the exact nuScenes radar layout."""
    from radarslam.sim.generate import simulate

    if jobs is not None and jobs < 1:
        raise ConfigError(f"--jobs {jobs}: must be >= 1")
    if seed is not None and seed < 0:
        raise ConfigError(f"--seed {seed}: must be >= 0 (numpy refuses negative seeds)")
    s = simulate(
        preset,
        out,
        seed=seed,
        progress=not quiet,
        overrides=list(set_),
        jobs=jobs,
        overwrite=overwrite,
        trajectory_tum=trajectory,
    )
    typer.echo(s.describe())
