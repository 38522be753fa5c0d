"""Exceptions whose message is one line naming the file or value and what is wrong.

The CLI prints ``error: <message>`` for these and exits with status 2; anything else is a bug.
"""

from __future__ import annotations


class RadarSlamError(Exception):
    """Base class: a user-facing error with a one-line message."""


class DataError(RadarSlamError):
    """A dataset file or table is missing, truncated or malformed."""


class ConfigError(RadarSlamError):
    """A configuration file or override is invalid."""


class CheckpointError(RadarSlamError):
    """A model checkpoint is missing, corrupt or does not match the requested model."""
