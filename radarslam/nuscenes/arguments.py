"""Checks of the reader's arguments, made at the call (not at the first frame or sweep read)."""

from __future__ import annotations

import numpy as np

from radarslam.errors import ConfigError, DataError
from radarslam.nuscenes.filters import RadarPointFilter
from radarslam.types import RADAR_CHANNELS


def _channel_index(channel: str) -> int:
    try:
        return RADAR_CHANNELS.index(channel)
    except ValueError:
        raise DataError(
            f"unknown radar channel {channel!r}; expected one of {RADAR_CHANNELS}"
        ) from None


def _check_filters(filters) -> None:
    if filters is not None and not isinstance(filters, RadarPointFilter):
        raise ConfigError(
            f"filters must be a RadarPointFilter or None, got {type(filters).__name__} {filters!r}"
        )


def _is_real(x) -> bool:
    return not isinstance(x, bool) and isinstance(x, (int, float, np.integer, np.floating))


def _check_sync_tolerance(sync_tolerance_us) -> None:
    if sync_tolerance_us is None:
        return
    if not _is_real(sync_tolerance_us) or not np.isfinite(sync_tolerance_us):
        raise ConfigError(
            f"sync_tolerance_us must be a finite number of microseconds > 0 or None, got "
            f"{sync_tolerance_us!r}"
        )
    if sync_tolerance_us <= 0:
        raise ConfigError(f"sync_tolerance_us must be > 0, got {sync_tolerance_us!r}")


def _channel_list(channels) -> list[str]:
    """``channels`` as a list: one channel name given as a bare string is one channel."""
    if isinstance(channels, str):
        return [channels]
    try:
        return list(channels)
    except TypeError:
        raise ConfigError(
            f"channels must be a radar channel name or a list of them, got {channels!r}"
        ) from None
