"""The file-level check of a checkpoint, without torch: a bad file given to a SLAM run fails
before the run, while torch and the weights load only once the other processes are working."""

from __future__ import annotations

import zipfile
from pathlib import Path

from radarslam.errors import CheckpointError


def check_archive(path: Path) -> None:
    """A checkpoint is a torch zip archive: anything else fails here with a short reason (torch's
    own messages for such files are several sentences about ``weights_only``)."""
    if path.is_dir():
        raise CheckpointError(f"{path}: is a folder, not a checkpoint file")
    try:
        with path.open("rb") as fh:
            head = fh.read(4)
        is_zip = zipfile.is_zipfile(path)
    except OSError as exc:
        raise CheckpointError(f"{path}: unreadable ({exc.strerror or exc})") from None
    if is_zip:
        try:
            with zipfile.ZipFile(path) as zf:
                names = zf.namelist()
        except (zipfile.BadZipFile, OSError, ValueError):
            raise CheckpointError(
                f"{path}: not a readable checkpoint (truncated or damaged zip archive)"
            ) from None
        if not any(n.endswith("/data.pkl") for n in names):  # torch.save writes <name>/data.pkl
            raise CheckpointError(
                f"{path}: not a radarslam checkpoint (a zip archive, but not torch's: "
                f"holds {', '.join(names[:3]) or 'nothing'}{', ...' if len(names) > 3 else ''})"
            )
        return
    if not head:
        raise CheckpointError(f"{path}: not a readable checkpoint (empty file)")
    if head.startswith(b"PK"):
        raise CheckpointError(
            f"{path}: not a readable checkpoint (truncated or damaged zip archive)"
        )
    raise CheckpointError(f"{path}: not a radarslam checkpoint (not a torch zip archive)")
