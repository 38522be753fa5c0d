"""Grouping the five radars' sweeps of a scene into frames, by time.

Works on rows of the compact radar index only: no file is read. The rule in words is in
:meth:`radarslam.nuscenes.reader.NuScenesRadar.iter_frames`.
"""

from __future__ import annotations

import numpy as np

#: Nominal ARS408 sweep period (13 Hz), used when a scene has too few sweeps to measure it.
NOMINAL_PERIOD_US = 76_923


def group_rows(
    timestamp_us: np.ndarray,
    rows: dict[int, np.ndarray],
    priority: list[int],
    sync_tolerance_us: int | None,
) -> list[list[tuple[int, int]]]:
    """Frames as lists of (channel index, row), anchor first.

    ``timestamp_us``: every radar row's time; ``rows``: each channel's rows of the scene in time
    order; ``priority``: channel indices, the reference channel first, then the order in which
    other channels provide anchors where it has gaps.
    """
    ref = priority[0]
    times = {c: timestamp_us[rows[c]] for c in priority}
    diffs = np.concatenate([np.diff(t) for t in times.values() if len(t) > 1] or [np.zeros(0)])
    period = float(np.median(diffs)) if len(diffs) >= 3 else float(NOMINAL_PERIOD_US)
    tol = period / 2 if sync_tolerance_us is None else float(sync_tolerance_us)

    # 1. anchors: the reference channel's sweeps, then other channels' sweeps that fall in a
    #    gap of all anchors so far (farther than 3/4 of a period from every anchor).
    anchor_t = np.zeros(0, dtype=np.int64)
    anchors: list[tuple[int, int]] = []  # (channel, row)
    is_anchor = {c: np.zeros(len(rows[c]), dtype=bool) for c in priority}
    for c in priority:
        t = times[c]
        if len(t) == 0:
            continue
        if c == ref or len(anchor_t) == 0:
            new = np.ones(len(t), dtype=bool)
        else:
            pos = np.searchsorted(anchor_t, t)
            left = np.abs(t - anchor_t[np.maximum(pos - 1, 0)])
            right = np.abs(anchor_t[np.minimum(pos, len(anchor_t) - 1)] - t)
            new = np.minimum(left, right) > 0.75 * period
        is_anchor[c] = new
        anchors += [(c, int(r)) for r in rows[c][new]]
        anchor_t = np.sort(np.concatenate([anchor_t, t[new]]))
    anchors.sort(key=lambda cr: int(timestamp_us[cr[1]]))
    a_time = np.array([timestamp_us[r] for _, r in anchors], dtype=np.int64)
    groups: list[list[tuple[int, int]]] = [[a] for a in anchors]
    taken = {a: {c} for a, (c, _) in enumerate(anchors)}

    # 2. every other channel: nearest sweep within tol, one-to-one, closest pairs first.
    for c in priority:
        t = times[c]
        free = np.flatnonzero(~is_anchor[c])
        if len(free) == 0 or len(a_time) == 0:
            continue
        pairs = []
        for k in free:
            lo = np.searchsorted(a_time, t[k] - tol, "left")
            hi = np.searchsorted(a_time, t[k] + tol, "right")
            for a in range(lo, hi):
                pairs.append((abs(int(a_time[a] - t[k])), a, int(k)))
        pairs.sort()
        used = set()
        for _, a, i in pairs:
            if i in used or c in taken[a]:
                continue
            used.add(i)
            taken[a].add(c)
            groups[a].append((c, int(rows[c][i])))
    return groups
