"""Reading a user's text file (a config, a trajectory, a results file) with one-line errors."""

from __future__ import annotations

from pathlib import Path

from radarslam.errors import DataError, RadarSlamError


def read_text(path: str | Path, what: str = "file", error: type[RadarSlamError] = DataError) -> str:
    """The UTF-8 text of ``path``; ``error`` naming the file when it is missing, unreadable or
    not text (``what`` says which kind of file was expected)."""
    path = Path(path)
    if path.is_dir():
        raise error(f"{path}: is a folder, not a {what}")
    if not path.is_file():
        raise error(f"{path}: {what} does not exist")
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise error(f"{path}: not a UTF-8 text file (a {what} was expected)") from None
    except OSError as exc:
        raise error(f"{path}: cannot read the {what} ({exc.strerror})") from None
