"""Integer-microsecond timestamps (nuScenes' unit) checked once for every API that takes them."""

from __future__ import annotations

import numpy as np

from radarslam.errors import DataError

#: |t| below this: t + any delta a caller adds cannot wrap in int64 (2^62 us is 146,000 years).
MAX_ABS_US = 2**62


def check_timestamps_us(values, n: int, what: str, strictly_increasing: bool = True) -> np.ndarray:
    """(n,) int64 integer microseconds, increasing (strictly, or allowing repeats), from integers
    or integral floats; anything else (seconds, NaN, strings, bools, out of range, out of order)
    is a :class:`DataError` naming ``what`` and the first offending value."""
    ts = np.asarray(values)
    if ts.ndim != 1 or len(ts) != n:
        raise DataError(f"{what}: {ts.shape} timestamps for {n} poses (need one per pose)")
    if ts.dtype == bool or not (
        np.issubdtype(ts.dtype, np.integer) or np.issubdtype(ts.dtype, np.floating)
    ):
        raise DataError(
            f"{what}: timestamps_us must be integer microseconds, got {ts.dtype} values"
            + (f" such as {ts.flat[0].item()!r}" if ts.size else "")
        )
    if not ts.size:
        return ts.astype(np.int64)
    if np.issubdtype(ts.dtype, np.floating):
        with np.errstate(invalid="ignore"):
            bad = ~np.isfinite(ts) | (ts != np.round(ts))
        if bad.any():
            i = int(np.argmax(bad))
            raise DataError(
                f"{what}: timestamp {i} is {ts[i].item()!r}; timestamps_us must be finite integer "
                "microseconds (seconds given? multiply by 1e6)"
            )
    big = np.abs(ts.astype(np.float64)) >= MAX_ABS_US
    if big.any():
        i = int(np.argmax(big))
        raise DataError(f"{what}: timestamp {i} ({ts[i].item()!r} us) is out of range (|t| < 2^62)")
    out = ts.astype(np.int64)
    steps = np.diff(out)
    wrong = steps <= 0 if strictly_increasing else steps < 0
    if wrong.any():
        i = int(np.argmax(wrong)) + 1
        how = "repeats" if steps[i - 1] == 0 else "is earlier than"
        order = "strictly increasing" if strictly_increasing else "sorted"
        raise DataError(
            f"{what}: timestamp {i} ({int(out[i])} us) {how} the previous one; timestamps must "
            f"be {order}"
        )
    return out
