"""Reading the five nuScenes radars without the devkit: sweeps, synchronised frames, accumulation.

:class:`NuScenesRadar` reads ``DATAROOT/<version>/*.json`` lazily (see :mod:`.tables`) and the radar
``.pcd`` files with :mod:`.pcd`. Points are returned in their sensor frame with the calibration
(``ego_from_sensor``) and the ground-truth ego pose of that very sample_data (``world_from_ego``).

Documented skips (never errors): points with a NaN/inf field are dropped, so are points farther
than :data:`MAX_POINT_COORDINATE_M` from their radar along any axis (an ARS408 sees at most ~250 m:
such a point is a corrupt value, and would put the map or a voxel key out of range), and a sweep
with no point left is returned as a :class:`RadarSweep` with 0 points. All are counted in
``reader.skip_counts`` and logged once per scene (logger ``radarslam.nuscenes``). The exception:
:meth:`NuScenesRadar.iter_frames` raises :class:`DataError` at the end of a scene whose every
sweep it read was empty (a scene without a single radar point is broken data, not a gap).

The point checks and :func:`stack_in_reference` are in :mod:`.sweeps`, the frame grouping rule in
:mod:`.frames` and the argument checks in :mod:`.arguments`.
"""

from __future__ import annotations

import itertools
import logging
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path

import numpy as np

from radarslam.errors import ConfigError, DataError
from radarslam.geometry import invert
from radarslam.nuscenes.arguments import (
    _channel_index,
    _channel_list,
    _check_filters,
    _check_sync_tolerance,
    _is_real,
)
from radarslam.nuscenes.filters import RadarPointFilter
from radarslam.nuscenes.frames import NOMINAL_PERIOD_US, group_rows
from radarslam.nuscenes.pcd import read_pcd
from radarslam.nuscenes.sweeps import (
    _FLOAT_FIELDS,
    _SKIP_KEYS,
    MAX_POINT_COORDINATE_M,
    SkipCounts,
    stack_in_reference,
)
from radarslam.nuscenes.tables import NuScenesTables
from radarslam.types import (
    RADAR_CHANNELS,
    AccumulatedCloud,
    RadarFrame,
    RadarSweep,
    SceneInfo,
)

# names callers import from here
__all__ = [
    "MAX_POINT_COORDINATE_M",
    "NOMINAL_PERIOD_US",
    "NuScenesRadar",
    "SkipCounts",
    "stack_in_reference",
]

log = logging.getLogger("radarslam.nuscenes")


class NuScenesRadar:
    """The radar side of one nuScenes version under ``dataroot`` (real or synthetic).

    ``filters`` (a :class:`RadarPointFilter`) is applied to every sweep the reader returns unless a
    method is given its own; the default is the devkit's (invalid_state 0, dyn_prop 0..6,
    ambig_state 3). ``use_cache``/``cache_dir``: see :class:`NuScenesTables`.
    """

    def __init__(
        self,
        dataroot: str | Path,
        version: str = "v1.0-mini",
        filters: RadarPointFilter | None = None,
        *,
        use_cache: bool = True,
        cache_dir: str | Path | None = None,
    ):
        self.filters = RadarPointFilter.devkit_default() if filters is None else filters
        if not isinstance(self.filters, RadarPointFilter):
            raise TypeError(f"filters must be a RadarPointFilter, got {type(filters).__name__}")
        self.tables = NuScenesTables(dataroot, version, use_cache=use_cache, cache_dir=cache_dir)
        self.dataroot = self.tables.dataroot
        self._root = str(self.dataroot)  # os.path.join per sweep: pathlib costs 40 us a file
        self.version = version
        self.skip_counts = SkipCounts()
        self._ego_from_sensor: dict[int, np.ndarray] = {}
        self._groups: tuple[np.ndarray, np.ndarray] | None = None
        self._keyframes: dict[int, dict[int, int]] | None = None
        self._scene_infos: list[SceneInfo] | None = None
        self._reported: set[str] = set()
        self._skipped_rows: set[int] = set()
        self._empty_rows: set[int] = set()  # sweeps with no point kept, before filtering

    # ---- scenes ------------------------------------------------------------------------------
    def scenes(self) -> list[SceneInfo]:
        """All scenes, in scene.json order."""
        if self._scene_infos is None:
            small = self.tables.small
            out = []
            for rec in small.scenes:
                lg = small.logs[rec["log_token"]]
                out.append(
                    SceneInfo(
                        name=rec["name"],
                        token=rec["token"],
                        log_token=rec["log_token"],
                        location=lg["location"],
                        date_captured=str(lg["date_captured"]),
                        vehicle=str(lg.get("vehicle", "")),
                        nbr_samples=int(rec.get("nbr_samples", 0)),
                        first_sample_token=rec["first_sample_token"],
                        last_sample_token=rec["last_sample_token"],
                        description=str(rec.get("description", "")),
                    )
                )
            self._scene_infos = out
        return list(self._scene_infos)

    def scene(self, name: str | SceneInfo) -> SceneInfo:
        """This reader's :class:`SceneInfo` of a scene name, or of a :class:`SceneInfo` (which
        must be one of this dataset's scenes: same name and token; :class:`DataError` naming
        both otherwise, e.g. a scene of another dataroot with the same name)."""
        if isinstance(name, SceneInfo):
            row = self.tables.small.scene_row.get(name.name)
            own = None if row is None else self.scenes()[row]
            if row is None or own is None or own.token != name.token:
                mine = f"its {name.name!r} has token {own.token!r}" if own else "no such name"
                raise DataError(
                    f"scene {name.name!r} (token {name.token!r}) is not a scene of "
                    f"{self.tables.table_dir} ({mine}): a SceneInfo from another dataset or "
                    "reader?"
                )
            self.tables.check_scene(row)
            return own
        if not isinstance(name, str):
            raise DataError(
                f"scene must be a scene name or a SceneInfo, got {type(name).__name__} {name!r}"
            )
        row = self.tables.small.scene_row.get(name)
        if row is None:
            names = [s.name for s in self.scenes()]
            few = ", ".join(names[:5]) + (", ..." if len(names) > 5 else "")
            raise DataError(
                f"unknown scene {name!r} in {self.tables.table_dir}; "
                f"{len(names)} scenes, e.g. {few or 'none'}"
            )
        self.tables.check_scene(row)  # a broken scene fails when asked for, not the others
        return self.scenes()[row]

    def scene_start_us(self, scene: str | SceneInfo) -> int:
        info = self.scene(scene)
        small = self.tables.small
        return int(small.sample_timestamp_us[small.sample_row[info.first_sample_token]])

    def locations(self) -> list[str]:
        return sorted({s.location for s in self.scenes()})

    def scenes_for_location(
        self, location: str, dates: Iterable[str] | None = None
    ) -> list[SceneInfo]:
        """Scenes recorded at ``location`` (optionally only on ``dates``, YYYY-MM-DD), sorted by
        date then start time: one call gives the session order of a multi-session run."""
        locs = self.locations()
        if location not in locs:
            raise DataError(f"unknown location {location!r}; the dataset has {locs}")
        wanted = None if dates is None else {str(d) for d in dates}
        out = [
            s
            for s in self.scenes()
            if s.location == location and (wanted is None or s.date_captured in wanted)
        ]
        return sorted(out, key=lambda s: (s.date_captured, self.scene_start_us(s), s.name))

    def samples(self, scene: str | SceneInfo) -> list[str]:
        """Sample tokens of a scene in time order (following ``next``)."""
        info = self.scene(scene)
        small = self.tables.small
        row = small.sample_row[info.first_sample_token]
        scene_row = small.scene_row[info.name]
        out = []
        while row >= 0 and small.sample_scene[row] == scene_row:
            out.append(small.sample_token[row].decode())
            if len(out) > len(small.sample_token):
                raise DataError(f"{self.tables.path('sample')}: sample next-chain has a cycle")
            row = int(small.sample_next[row])
        return out

    # ---- sweeps ------------------------------------------------------------------------------
    def _scene_channel_rows(self, scene_row: int, ch: int) -> np.ndarray:
        """Rows of one scene/channel in chain order (prev/next), checked to be in time order."""
        radar = self.tables.radar
        if self._groups is None:
            sc = self.tables.small.sample_scene[radar.sample]
            order = np.lexsort((radar.timestamp_us, radar.channel, sc))
            gkey = sc[order].astype(np.int64) * 16 + radar.channel[order]
            self._groups = (order, gkey)
        order, gkey = self._groups
        k = scene_row * 16 + ch
        lo, hi = np.searchsorted(gkey, k, "left"), np.searchsorted(gkey, k, "right")
        members = order[lo:hi]
        if len(members) == 0:
            return members
        member_set = set(members.tolist())
        heads = [int(r) for r in members if int(radar.prev[r]) not in member_set]
        heads.sort(key=lambda r: int(radar.timestamp_us[r]))
        rows: list[int] = []
        for h in heads:
            r = h
            while r >= 0 and r in member_set:
                rows.append(r)
                member_set.discard(r)
                r = int(radar.next[r])
        if member_set or len(rows) != len(members):
            raise DataError(
                f"{self.tables.path('sample_data')}: the prev/next chain of "
                f"{RADAR_CHANNELS[ch]} in scene {self.tables.small.scenes[scene_row]['name']!r} "
                f"has a cycle"
            )
        out = np.asarray(rows, dtype=np.int64)
        if len(heads) > 1:
            log.warning(
                "%s of scene %s: prev/next chain is broken into %d pieces; joined in time order",
                RADAR_CHANNELS[ch],
                self.tables.small.scenes[scene_row]["name"],
                len(heads),
            )
        ts = radar.timestamp_us[out]
        if len(ts) > 1 and (np.diff(ts) <= 0).any():
            i = int(np.flatnonzero(np.diff(ts) <= 0)[0])
            raise DataError(
                f"{self.tables.path('sample_data')}: {RADAR_CHANNELS[ch]} sweep "
                f"{radar.token[out[i + 1]].decode()!r} is not later than its prev"
            )
        return out

    def _rows(self, scene: str | SceneInfo, channel: str) -> np.ndarray:
        info = self.scene(scene)
        return self._scene_channel_rows(
            self.tables.small.scene_row[info.name], _channel_index(channel)
        )

    def _sweep(
        self,
        row: int,
        filters: RadarPointFilter | None = None,
        scene_name: str | None = None,
    ) -> RadarSweep:
        tables = self.tables
        radar = tables.radar
        filename = radar.filename[row].decode("utf-8")
        points = read_pcd(os.path.join(self._root, filename))
        empty = len(points) == 0
        nan_dropped = far_dropped = 0
        if len(points):
            finite = np.ones(len(points), dtype=bool)
            for name in _FLOAT_FIELDS:
                finite &= np.isfinite(points[name])
            near = finite.copy()
            for name in ("x", "y", "z"):
                with np.errstate(invalid="ignore"):  # NaN: already dropped
                    near &= np.abs(points[name]) <= MAX_POINT_COORDINATE_M
            if not near.all():
                nan_dropped = int((~finite).sum())
                far_dropped = int((finite & ~near).sum())
                points = points[near]
                empty = len(points) == 0
        if empty:
            self._empty_rows.add(row)
        if (nan_dropped or far_dropped or empty) and row not in self._skipped_rows:
            self._skipped_rows.add(row)  # counted once per sweep, however often it is read
            if scene_name is None:
                small = tables.small
                scene_name = small.scenes[small.sample_scene[radar.sample[row]]]["name"]
            self.skip_counts.add(scene_name, nan_dropped, empty, far_dropped)
        points = (self.filters if filters is None else filters).apply(points)
        cs = int(radar.calibrated_sensor[row])
        ego_from_sensor = self._ego_from_sensor.get(cs)
        if ego_from_sensor is None:
            ego_from_sensor = self._ego_from_sensor[cs] = tables.ego_from_sensor(cs)
        return RadarSweep(
            channel=RADAR_CHANNELS[int(radar.channel[row])],
            timestamp_us=int(radar.timestamp_us[row]),
            points=points,
            ego_from_sensor=ego_from_sensor.copy(),
            world_from_ego=tables.world_from_ego(row),
            is_key_frame=bool(radar.is_key_frame[row]),
            token=radar.token[row].decode(),
            sample_token=tables.small.sample_token[radar.sample[row]].decode(),
            filename=filename,
        )

    def _row_of(self, sample_data_token: str) -> int:
        row = self.tables.radar_tokens.find(sample_data_token)
        if row < 0:
            raise DataError(
                f"sample_data token {sample_data_token!r} is not a radar record of "
                f"{self.tables.path('sample_data')}"
            )
        return row

    def load_sweep(
        self, sample_data_token: str, filters: RadarPointFilter | None = None
    ) -> RadarSweep:
        """One radar sweep by its sample_data token (reader's filters unless ``filters``)."""
        _check_filters(filters)
        return self._sweep(self._row_of(sample_data_token), filters)

    def _report_skips(self, scene_name: str, before: dict[str, int] | None) -> None:
        now = self.skip_counts.per_scene.get(scene_name)
        if now is None:
            return
        before = before or dict.fromkeys(_SKIP_KEYS, 0)
        d_nan = now["nan_points"] - before["nan_points"]
        d_empty = now["empty_sweeps"] - before["empty_sweeps"]
        d_far = now["far_points"] - before["far_points"]
        if d_nan or d_empty or d_far:
            # a warning the first time a scene shows skips, then debug: stats and multi-channel
            # passes would otherwise repeat it once per radar
            first = scene_name not in self._reported
            self._reported.add(scene_name)
            far = (
                f", {d_far} point(s) farther than {MAX_POINT_COORDINATE_M:g} m from their radar "
                "dropped"
                if d_far
                else ""
            )
            log.log(
                logging.WARNING if first else logging.DEBUG,
                "scene %s: %d empty sweep(s) yielded with 0 points, %d point(s) with NaN fields "
                "dropped%s",
                scene_name,
                d_empty,
                d_nan,
                far,
            )

    def iter_sweeps(
        self,
        scene: str | SceneInfo,
        channel: str,
        key_frames_only: bool = False,
        filters: RadarPointFilter | None = None,
    ) -> Iterator[RadarSweep]:
        """The sweeps of one radar in a scene, following the sample_data prev/next chain (time
        order). Points are in the sensor frame, after the reader's filters (or ``filters``).
        The arguments are checked at the call, not at the first sweep."""
        _check_filters(filters)
        info = self.scene(scene)
        rows = self._rows(info, channel)
        if key_frames_only:
            rows = rows[self.tables.radar.is_key_frame[rows]]
        return self._sweeps(info, rows, filters)

    def _sweeps(self, info: SceneInfo, rows: np.ndarray, filters) -> Iterator[RadarSweep]:
        before = dict(self.skip_counts.per_scene.get(info.name, {})) or None
        for r in rows:
            yield self._sweep(int(r), filters, info.name)
        self._report_skips(info.name, before)

    def scene_extrinsics(self, scene: str | SceneInfo) -> dict[str, np.ndarray]:
        """Each radar's ``ego_from_sensor`` at its first sweep of the scene (4x4; radars
        without a sweep there are absent; no file is read)."""
        scene_row = self.tables.small.scene_row[self.scene(scene).name]
        out = {}
        for c, ch in enumerate(RADAR_CHANNELS):
            rows = self._scene_channel_rows(scene_row, c)
            if len(rows):
                cs = int(self.tables.radar.calibrated_sensor[rows[0]])
                out[ch] = self.tables.ego_from_sensor(cs)
        return out

    def sweep_tokens(self, scene: str | SceneInfo, channel: str) -> list[str]:
        """sample_data tokens of one radar in a scene, in time order (no file is read)."""
        return [self.tables.radar.token[r].decode() for r in self._rows(scene, channel)]

    def sweep_files(self, scene: str | SceneInfo, channel: str) -> list[tuple[str, int]]:
        """(filename relative to the dataroot, timestamp in us) of each sweep of one radar in a
        scene, in time order (no file is read)."""
        radar = self.tables.radar
        return [
            (radar.filename[r].decode("utf-8"), int(radar.timestamp_us[r]))
            for r in self._rows(scene, channel)
        ]

    # ---- frames ------------------------------------------------------------------------------
    def _keyframe_rows(self) -> dict[int, dict[int, int]]:
        """sample row -> {channel index: key-frame sample_data row}."""
        if self._keyframes is None:
            radar = self.tables.radar
            out: dict[int, dict[int, int]] = {}
            for r in np.flatnonzero(radar.is_key_frame):
                out.setdefault(int(radar.sample[r]), {})[int(radar.channel[r])] = int(r)
            self._keyframes = out
        return self._keyframes

    def frame_groups(
        self,
        scene: str | SceneInfo,
        ref_channel: str = "RADAR_FRONT",
        sync_tolerance_us: int | None = None,
    ) -> list[dict[str, str]]:
        """The grouping :meth:`iter_frames` uses, as lists of {channel: sample_data token}, anchor
        channel first (no file is read)."""
        _check_sync_tolerance(sync_tolerance_us)
        return [
            {RADAR_CHANNELS[c]: self.tables.radar.token[r].decode() for c, r in g}
            for g in self._group_rows(self.scene(scene), ref_channel, sync_tolerance_us)
        ]

    def frame_count(
        self,
        scene: str | SceneInfo,
        ref_channel: str = "RADAR_FRONT",
        sync_tolerance_us: int | None = None,
    ) -> int:
        """How many frames :meth:`iter_frames` yields for the scene (no file is read)."""
        _check_sync_tolerance(sync_tolerance_us)
        return len(self._group_rows(self.scene(scene), ref_channel, sync_tolerance_us))

    def _group_rows(
        self, info: SceneInfo, ref_channel: str, sync_tolerance_us: int | None
    ) -> list[list[tuple[int, int]]]:
        ref = _channel_index(ref_channel)
        priority = [ref] + [c for c in range(len(RADAR_CHANNELS)) if c != ref]
        scene_row = self.tables.small.scene_row[info.name]
        rows = {c: self._scene_channel_rows(scene_row, c) for c in priority}
        return group_rows(self.tables.radar.timestamp_us, rows, priority, sync_tolerance_us)

    def iter_frames(
        self,
        scene: str | SceneInfo,
        key_frames_only: bool = False,
        ref_channel: str = "RADAR_FRONT",
        sync_tolerance_us: int | None = None,
        filters: RadarPointFilter | None = None,
        stride: int = 1,
    ) -> Iterator[RadarFrame]:
        """Sets of the five radars' sweeps nearest in time (~13 Hz), in time order.

        Grouping rule:

        * Frames are anchored on the reference channel's sweeps. Where the reference channel has
          a gap (or before its first / after its last sweep), the next channel in
          ``RADAR_CHANNELS`` order that has sweeps there provides the anchors: a sweep becomes an
          anchor when it is farther than 3/4 of a sweep period from every anchor chosen so far.
        * Every other channel contributes to an anchor its sweep nearest in time if within
          ``sync_tolerance_us`` (default: half the scene's median sweep period, ~38 ms); pairs are
          assigned closest first, and each sweep is used at most once, so a channel whose sweep
          has no anchor near it is just absent from ``frame.sweeps``.
        * The frame's ``timestamp_us`` and ``world_from_ego`` are the anchor sweep's; it is a key
          frame (with ``sample_token``) when the anchor sweep is.

        ``key_frames_only=True`` instead yields one frame per sample of the scene, made of each
        channel's key-frame sample_data, anchored on the reference channel's (or, if absent, the
        first channel present in ``RADAR_CHANNELS`` order); samples without any radar key frame
        are skipped.

        Empty sweeps are yielded (and counted in ``skip_counts``), but when every sweep of the
        scene's frames was empty, :class:`DataError` is raised after the last frame.

        ``stride`` k > 1 yields every k-th of those frames (the first, the (k+1)-th, ...) and
        reads only their sweeps: a calibration pass that needs fewer frames does not pay for
        reading the others.

        Arguments are checked at the call (:class:`DataError` / :class:`ConfigError`), not at
        the first frame.
        """
        info = self.scene(scene)
        _channel_index(ref_channel)
        _check_sync_tolerance(sync_tolerance_us)
        _check_filters(filters)
        if isinstance(stride, bool) or not isinstance(stride, (int, np.integer)) or stride < 1:
            raise ConfigError(f"iter_frames: stride must be an integer >= 1, got {stride!r}")
        return self._iter_frames(
            info, key_frames_only, ref_channel, sync_tolerance_us, filters, int(stride)
        )

    def _iter_frames(
        self,
        info: SceneInfo,
        key_frames_only: bool,
        ref_channel: str,
        sync_tolerance_us: int | None,
        filters: RadarPointFilter | None,
        stride: int = 1,
    ) -> Iterator[RadarFrame]:
        before = dict(self.skip_counts.per_scene.get(info.name, {})) or None
        if key_frames_only:
            yield from itertools.islice(
                self._iter_key_frames(info, ref_channel, filters), 0, None, stride
            )
        else:
            groups = self._group_rows(info, ref_channel, sync_tolerance_us)[::stride]
            for group in groups:
                sweeps = [self._sweep(r, filters, info.name) for _, r in group]
                anchor = sweeps[0]
                yield RadarFrame(
                    timestamp_us=anchor.timestamp_us,
                    sweeps={
                        s.channel: s
                        for s in sorted(sweeps, key=lambda s: RADAR_CHANNELS.index(s.channel))
                    },
                    world_from_ego=anchor.world_from_ego,
                    scene_name=info.name,
                    is_key_frame=anchor.is_key_frame,
                    sample_token=anchor.sample_token if anchor.is_key_frame else "",
                )
            rows = [r for g in groups for _, r in g]
            if rows and self._empty_rows.issuperset(rows):
                # partial emptiness is real (and counted); a whole scene without a point is not
                first = self.tables.radar.filename[rows[0]].decode("utf-8")
                raise DataError(
                    f"scene {info.name!r}: all {len(rows)} radar sweeps are empty (no point with "
                    f"finite values within {MAX_POINT_COORDINATE_M:g} m), e.g. "
                    f"{os.path.join(self._root, first)}"
                )
        self._report_skips(info.name, before)

    def _iter_key_frames(
        self, info: SceneInfo, ref_channel: str, filters: RadarPointFilter | None
    ) -> Iterator[RadarFrame]:
        ref = _channel_index(ref_channel)
        priority = [ref] + [c for c in range(len(RADAR_CHANNELS)) if c != ref]
        kf = self._keyframe_rows()
        small = self.tables.small
        for tok in self.samples(info):
            chans = kf.get(small.sample_row[tok], {})
            present = [c for c in priority if c in chans]
            if not present:
                continue
            sweeps = {c: self._sweep(chans[c], filters, info.name) for c in present}
            anchor = sweeps[present[0]]
            yield RadarFrame(
                timestamp_us=anchor.timestamp_us,
                sweeps={RADAR_CHANNELS[c]: sweeps[c] for c in sorted(present)},
                world_from_ego=anchor.world_from_ego,
                scene_name=info.name,
                is_key_frame=True,
                sample_token=tok,
            )

    # ---- accumulation ------------------------------------------------------------------------
    def accumulate(
        self,
        sample_token: str,
        nsweeps: int = 7,
        channels: Sequence[str] = RADAR_CHANNELS,
        ref_channel: str | None = "RADAR_FRONT",
        min_distance_m: float = 1.0,
        point_mask: Callable[[RadarSweep], np.ndarray] | None = None,
        filters: RadarPointFilter | None = None,
    ) -> AccumulatedCloud:
        """Several sweeps of several radars in one reference frame at a key frame (AutoPlace /
        devkit ``from_file_multisweep``).

        For each channel: start at the sample's key-frame sweep, follow ``prev`` back for up to
        ``nsweeps`` sweeps (fewer at the scene start); drop points with ``|x| < min_distance_m and
        |y| < min_distance_m`` in their own sensor frame (the devkit's ``remove_close`` square),
        then ``point_mask(sweep)`` if given (e.g. dynamic-point removal); transform sensor ->
        ego(t_sweep) -> world -> ego(t_ref) -> reference sensor at the key frame.

        Unlike the devkit, which moves positions only, the velocity vectors (vx, vy) and
        (vx_comp, vy_comp) are rotated into the reference frame with the points (taken as
        (vx, vy, 0) and rotated in 3-D; the z part is dropped).

        ``ref_channel=None``: the reference is the ego frame at the key-frame sweep of the first
        of ``channels`` (in ``RADAR_CHANNELS`` order) present in the sample; that sweep's time is
        the reference time. ``time_lag_s`` = reference time - sweep time (>= 0 for past sweeps).
        """
        small = self.tables.small
        s_row = small.sample_row.get(sample_token)
        if s_row is None:
            raise DataError(f"sample token {sample_token!r} is not in {self.tables.path('sample')}")
        if isinstance(nsweeps, bool) or not isinstance(nsweeps, (int, np.integer)) or nsweeps < 1:
            raise ConfigError(f"nsweeps must be an integer >= 1, got {nsweeps!r}")
        if not _is_real(min_distance_m) or not np.isfinite(min_distance_m) or min_distance_m < 0:
            raise ConfigError(
                f"min_distance_m must be a finite number >= 0, got {min_distance_m!r}"
            )
        _check_filters(filters)
        channels = _channel_list(channels)
        ch_idx = [_channel_index(c) for c in channels]
        kf = self._keyframe_rows().get(s_row, {})
        if ref_channel is not None:
            ref_c = _channel_index(ref_channel)
            if ref_c not in kf:
                raise DataError(f"sample {sample_token!r} has no {ref_channel} key-frame sweep")
            ref_row = kf[ref_c]
        else:
            present = [c for c in sorted(ch_idx) if c in kf]
            if not present:
                raise DataError(
                    f"sample {sample_token!r} has no key-frame sweep of {list(channels)}"
                )
            ref_row = kf[present[0]]
        tables = self.tables
        radar = tables.radar
        world_from_ref = tables.world_from_ego(ref_row)
        if ref_channel is not None:
            world_from_ref = world_from_ref @ tables.ego_from_sensor(
                int(radar.calibrated_sensor[ref_row])
            )
        ref_from_world = invert(world_from_ref)
        ref_time_us = int(radar.timestamp_us[ref_row])
        scene_name = small.scenes[small.sample_scene[s_row]]["name"]

        parts: list[tuple[np.ndarray, np.ndarray, int, int, float]] = []
        counts: dict[tuple[str, int], int] = {}
        for c in ch_idx:
            row = kf.get(c, -1)
            k = 0
            while row >= 0 and k < nsweeps:
                sweep = self._sweep(row, filters, scene_name)
                pts = sweep.points
                if len(pts):
                    close = (np.abs(pts["x"]) < min_distance_m) & (
                        np.abs(pts["y"]) < min_distance_m
                    )
                    keep = ~close
                    if point_mask is not None:
                        m = np.asarray(point_mask(sweep))
                        if m.dtype != bool or m.shape != (len(pts),):
                            raise ValueError(
                                f"point_mask must return a bool array of shape ({len(pts)},), "
                                f"got {m.dtype} {m.shape}"
                            )
                        keep &= m
                    pts = pts[keep]
                parts.append(
                    (
                        pts,
                        ref_from_world @ sweep.world_from_sensor,
                        c,
                        k,
                        (ref_time_us - sweep.timestamp_us) * 1e-6,
                    )
                )
                counts[(RADAR_CHANNELS[c], k)] = len(pts)
                k += 1
                row = int(radar.prev[row])
                if row >= 0 and small.sample_scene[radar.sample[row]] != small.sample_scene[s_row]:
                    break  # the chain crosses a scene boundary: the scene starts here
        return AccumulatedCloud(
            points=stack_in_reference(parts),
            world_from_ref=world_from_ref,
            ref_channel=ref_channel,
            timestamp_us=ref_time_us,
            sample_token=sample_token,
            num_points_per_sweep=counts,
        )
