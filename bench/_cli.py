"""What every benchmark script does with a user error: one line, exit status 2."""

from __future__ import annotations

import sys
from collections.abc import Callable


def guarded(main: Callable[[], object]) -> None:
    """Run ``main``; a :class:`~radarslam.errors.RadarSlamError` (a bad ``--set``, a missing
    or malformed dataroot, a bad checkpoint) prints ``error: <message>`` and exits with 2."""
    from radarslam.errors import RadarSlamError

    try:
        code = main()
    except RadarSlamError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    if isinstance(code, int) and code:
        sys.exit(code)
