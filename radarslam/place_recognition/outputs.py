"""Up-front checks of output paths, so that a command fails before its work, not after it."""

from __future__ import annotations

from pathlib import Path

from radarslam.errors import ConfigError


def _first_existing(path: Path) -> Path:
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def check_output_dir(path: str | Path) -> Path:
    """``path`` is an existing directory or can be created as one (no file in the way)."""
    path = Path(path)
    if path.exists():
        if not path.is_dir():
            raise ConfigError(f"{path}: output directory is an existing file")
        return path
    blocker = _first_existing(path.parent)
    if not blocker.is_dir():
        raise ConfigError(
            f"{blocker}: is an existing file, so output directory {path} cannot be created"
        )
    return path


def check_output_file(path: str | Path) -> Path:
    """``path`` can be written as a file: not a directory, and its folder can exist."""
    path = Path(path)
    if path.is_dir():
        raise ConfigError(f"{path}: output file is an existing directory")
    parent = path.parent
    if parent.exists() and not parent.is_dir():
        raise ConfigError(f"{parent}: output directory is an existing file")
    blocker = _first_existing(parent)
    if not blocker.is_dir():
        raise ConfigError(f"{blocker}: is an existing file, so {path} cannot be written")
    return path
