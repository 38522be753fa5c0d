"""Naming rules of a results folder (layout: docs/outputs.md), shared by the code that writes one
(:mod:`radarslam.slam.outputs`) and the code that reads one (:mod:`radarslam.eval.evaluate`)."""

from __future__ import annotations

import re

from radarslam.errors import DataError

#: The ``format`` tag of ``run.json``.
RESULTS_FORMAT = "radarslam-results/1"
_SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")


def check_session_name(name: str) -> str:
    """``name`` when it can be part of a file name; DataError otherwise."""
    if not _SAFE_NAME.match(name or ""):
        raise DataError(
            f"session name {name!r} cannot be used in file names (letters, digits, _ . - only)"
        )
    return name
