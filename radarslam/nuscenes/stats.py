"""Radar statistics of any dataroot, side by side with the figures measured on real nuScenes.

Every statistic is computed on the raw points of each sweep (all 125 clusters on real data, NaN
points dropped) unless it says "after the default filters" (the devkit's: invalid_state 0,
dyn_prop 0..6, ambig_state 3). A point is "moving" when its compensated radial speed
``|u . v_comp|`` exceeds 1 m/s, "static" otherwise.

* Doppler-oracle consistency: on real files ``u . (v - v_comp) = -u . v_sensor`` holds for one
  sensor velocity per sweep. We fit that velocity by least squares per sweep and report the RMS
  residual (m/s); 0 means exact.
* Landmark re-detection: the static points of a sweep (after the default filters), moved to the
  world frame with the ground-truth poses, that have a detection of the same radar (after the
  default filters) within 1.0 m in the next sweep, and in any of the next 3 sweeps.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field

import numpy as np

from radarslam.nuscenes.filters import RadarPointFilter
from radarslam.types import RADAR_CHANNELS, RadarSweep

TANGENTIAL_MIN_SENSOR_SPEED_MPS = 2.0
MOVING_SPEED_MPS = 1.0
REDETECT_RADIUS_M = 1.0
REDETECT_LOOKAHEAD = 3

#: Figures from docs (nuscenes-radar-format.md), measured on real nuScenes radar files.
REAL_NUSCENES: dict[str, str] = {
    "points_per_sweep": "125 (every sweep)",
    "points_per_sweep_filtered": "~60 (roughly half)",
    "range_p50_m": "44-76",
    "range_max_m": "93-214",
    "rcs_p5_dbsm": "about -4",
    "rcs_p50_dbsm": "2-7",
    "rcs_p95_dbsm": "15-23",
    "invalid_state_0": "55-60 %",
    "ambig_state_3": "80-98 %",
    "dyn_prop_mostly": "1 and 3",
    "tangential_p50_mps": "2.3-2.6",
    "doppler_oracle_rms_mps": "0 (exact)",
}


@dataclass
class DatasetStats:
    dataroot: str
    version: str
    num_scenes: int = 0
    num_sweeps: int = 0
    num_points: int = 0
    points_per_sweep_mean: float = float("nan")
    points_per_sweep_min: int = 0
    points_per_sweep_max: int = 0
    filtered_points_per_sweep_mean: float = float("nan")
    filtered_fraction: float = float("nan")
    range_percentiles_m: dict[str, float] = field(default_factory=dict)  # p5, p50, p95, max
    rcs_percentiles_dbsm: dict[str, float] = field(default_factory=dict)  # p5, p50, p95
    dyn_prop_hist: dict[int, float] = field(default_factory=dict)  # value -> fraction
    invalid_state_hist: dict[int, float] = field(default_factory=dict)
    ambig_state_hist: dict[int, float] = field(default_factory=dict)
    moving_fraction: float = float("nan")
    tangential_speed_p50_mps: float = float("nan")
    doppler_oracle_rms_p50_mps: float = float("nan")  # median over sweeps of the per-sweep RMS
    doppler_oracle_rms_p95_mps: float = float("nan")
    redetect_next: float = float("nan")
    redetect_within_3: float = float("nan")
    redetect_sources: int = 0  # static points that had a next sweep to look in
    empty_sweeps: int = 0  # sweeps read with no (finite) point
    nan_points: int = 0  # points with NaN fields dropped by the reader in these scenes

    def to_dict(self) -> dict:
        d = asdict(self)
        for k in ("dyn_prop_hist", "invalid_state_hist", "ambig_state_hist"):
            d[k] = {str(a): b for a, b in d[k].items()}
        return d

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2, allow_nan=True)

    def to_markdown(self) -> str:
        def f(x, fmt="{:.2f}"):
            return (
                "n/a"
                if x is None or (isinstance(x, float) and not np.isfinite(x))
                else fmt.format(x)
            )

        def pct(x):
            return f(100 * x if x is not None else None, "{:.1f} %")

        def hist(h):
            top = sorted(h.items(), key=lambda kv: -kv[1])[:4]
            return ", ".join(f"{k}: {100 * v:.0f} %" for k, v in top) or "n/a"

        r, c = self.range_percentiles_m, self.rcs_percentiles_dbsm
        rows = [
            ("sweeps / points read", f"{self.num_sweeps} / {self.num_points}", ""),
            (
                "points per sweep (mean, min-max)",
                f"{f(self.points_per_sweep_mean, '{:.1f}')} "
                f"({self.points_per_sweep_min}-{self.points_per_sweep_max})",
                REAL_NUSCENES["points_per_sweep"],
            ),
            (
                "after default filters (mean)",
                f"{f(self.filtered_points_per_sweep_mean, '{:.1f}')} "
                f"({pct(self.filtered_fraction)})",
                REAL_NUSCENES["points_per_sweep_filtered"],
            ),
            ("range p50 (m)", f(r.get("p50")), REAL_NUSCENES["range_p50_m"]),
            (
                "range p5 / p95 / max (m)",
                " / ".join(f(r.get(k)) for k in ("p5", "p95", "max")),
                f"max {REAL_NUSCENES['range_max_m']}",
            ),
            ("RCS p5 (dBsm)", f(c.get("p5")), REAL_NUSCENES["rcs_p5_dbsm"]),
            ("RCS p50 (dBsm)", f(c.get("p50")), REAL_NUSCENES["rcs_p50_dbsm"]),
            ("RCS p95 (dBsm)", f(c.get("p95")), REAL_NUSCENES["rcs_p95_dbsm"]),
            (
                "invalid_state = 0",
                pct(self.invalid_state_hist.get(0, 0.0)),
                REAL_NUSCENES["invalid_state_0"],
            ),
            ("invalid_state (top)", hist(self.invalid_state_hist), "4, 9, 11, 16 common"),
            (
                "ambig_state = 3",
                pct(self.ambig_state_hist.get(3, 0.0)),
                REAL_NUSCENES["ambig_state_3"],
            ),
            ("dyn_prop (top)", hist(self.dyn_prop_hist), REAL_NUSCENES["dyn_prop_mostly"]),
            ("moving points (abs(u.v_comp) > 1 m/s)", pct(self.moving_fraction), "-"),
            (
                "tangential raw velocity p50, sensor moving (m/s)",
                f(self.tangential_speed_p50_mps),
                REAL_NUSCENES["tangential_p50_mps"],
            ),
            (
                "Doppler oracle RMS p50 / p95 (m/s)",
                f"{f(self.doppler_oracle_rms_p50_mps, '{:.3f}')} / "
                f"{f(self.doppler_oracle_rms_p95_mps, '{:.3f}')}",
                REAL_NUSCENES["doppler_oracle_rms_mps"],
            ),
            ("static landmark re-detected, next sweep", pct(self.redetect_next), "-"),
            ("... within the next 3 sweeps", pct(self.redetect_within_3), "-"),
            ("empty sweeps / NaN points skipped", f"{self.empty_sweeps} / {self.nan_points}", "-"),
        ]
        lines = [
            f"Radar statistics of {self.dataroot} ({self.version}, {self.num_scenes} scenes)",
            "",
            "| statistic | measured | real nuScenes |",
            "|---|---|---|",
        ]
        lines += [f"| {a} | {b} | {c_} |" for a, b, c_ in rows]
        return "\n".join(lines) + "\n"


def _unit(xy: np.ndarray) -> np.ndarray:
    r = np.linalg.norm(xy, axis=1, keepdims=True)
    return xy / np.maximum(r, 1e-9)


def _oracle_fit(sweep: RadarSweep) -> tuple[float, float] | None:
    """(RMS residual of u . (v - v_comp) = -u . v_sensor, |v_sensor|), v_sensor fitted per sweep."""
    if len(sweep) < 3:
        return None
    u = sweep.unit_directions
    d = np.einsum("ij,ij->i", u, sweep.velocity - sweep.velocity_comp)
    vs, *_ = np.linalg.lstsq(-u, d, rcond=None)
    res = d + u @ vs
    return float(np.sqrt(np.mean(res**2))), float(np.linalg.norm(vs))


def _static_world(sweep: RadarSweep, default: RadarPointFilter) -> tuple[np.ndarray, np.ndarray]:
    """(static points, all points) of a sweep after the default filters, in world xy."""
    s = sweep.with_points(default.apply(sweep.points))
    if len(s) == 0:
        z = np.zeros((0, 2))
        return z, z
    u = s.unit_directions
    static = np.abs(np.einsum("ij,ij->i", u, s.velocity_comp)) <= MOVING_SPEED_MPS
    w = s.xy @ s.world_from_sensor[:2, :2].T + s.world_from_sensor[:2, 3]
    return w[static], w


def _has_neighbour(src: np.ndarray, dst: np.ndarray, radius: float) -> np.ndarray:
    if len(src) == 0 or len(dst) == 0:
        return np.zeros(len(src), dtype=bool)
    d2 = ((src[:, None, :] - dst[None, :, :]) ** 2).sum(-1)
    return d2.min(axis=1) <= radius * radius


def dataset_statistics(
    reader,
    scenes: Sequence[str] | None = None,
    max_sweeps_per_scene: int | None = None,
    progress: bool = True,
) -> DatasetStats:
    """Statistics of the radar sweeps of ``scenes`` (default: all) of a :class:`NuScenesRadar`.

    ``max_sweeps_per_scene`` caps the sweeps read per radar and scene (the first ones in time).
    """
    from tqdm import tqdm

    default = RadarPointFilter.devkit_default()
    none = RadarPointFilter.none()
    infos = [reader.scene(s) for s in scenes] if scenes else reader.scenes()
    counts, counts_f = [], []
    ranges, rcs, dyn, inval, ambig = [], [], [], [], []
    moving, tangential, oracle = [], [], []
    hit1, hit3, n_src = 0, 0, 0
    for info in tqdm(
        infos, desc="radar statistics", unit="scene", disable=None if progress else True
    ):
        for ch in RADAR_CHANNELS:
            window: list[tuple[np.ndarray, np.ndarray]] = []  # (static, all) world xy per sweep
            for k, sweep in enumerate(reader.iter_sweeps(info, ch, filters=none)):
                if max_sweeps_per_scene is not None and k >= max_sweeps_per_scene:
                    break
                p = sweep.points
                counts.append(len(p))
                counts_f.append(int(default.mask(p).sum()))
                if len(p):
                    xy, u = sweep.xy, sweep.unit_directions
                    ranges.append(np.linalg.norm(xy, axis=1))
                    rcs.append(p["rcs"].astype(np.float64))
                    dyn.append(p["dyn_prop"])
                    inval.append(p["invalid_state"])
                    ambig.append(p["ambig_state"])
                    moving.append(np.abs(np.einsum("ij,ij->i", u, sweep.velocity_comp)) > 1.0)
                    o = _oracle_fit(sweep)
                    if o is not None:
                        oracle.append(o[0])
                    # The real reference figure comes from a moving car: a standing ego (a
                    # quarter of the time in the city) would pull the median towards 0.
                    if o is not None and o[1] > TANGENTIAL_MIN_SENSOR_SPEED_MPS:
                        perp = np.column_stack([-u[:, 1], u[:, 0]])
                        tangential.append(np.abs(np.einsum("ij,ij->i", perp, sweep.velocity)))
                window.append(_static_world(sweep, default))
                # the sweep REDETECT_LOOKAHEAD back now has all its look-ahead sweeps
                if len(window) > REDETECT_LOOKAHEAD:
                    a, b, c = _redetect(window[0][0], [w[1] for w in window[1:]])
                    hit1, hit3, n_src = hit1 + a, hit3 + b, n_src + c
                    window.pop(0)
            while len(window) > 1:  # the last sweeps of the chain, with fewer sweeps after them
                a, b, c = _redetect(window[0][0], [w[1] for w in window[1:]])
                hit1, hit3, n_src = hit1 + a, hit3 + b, n_src + c
                window.pop(0)

    st = DatasetStats(dataroot=str(reader.dataroot), version=reader.version, num_scenes=len(infos))
    st.num_sweeps = len(counts)
    st.num_points = int(sum(counts))
    st.empty_sweeps = sum(1 for c in counts if c == 0)
    # NaN points are dropped inside the reader; its per-scene counts cover each sweep once
    st.nan_points = sum(
        reader.skip_counts.per_scene.get(i.name, {}).get("nan_points", 0) for i in infos
    )
    if counts:
        st.points_per_sweep_mean = float(np.mean(counts))
        st.points_per_sweep_min, st.points_per_sweep_max = int(min(counts)), int(max(counts))
        st.filtered_points_per_sweep_mean = float(np.mean(counts_f))
        st.filtered_fraction = float(sum(counts_f) / max(sum(counts), 1))
    if ranges:
        rng_all, rcs_all = np.concatenate(ranges), np.concatenate(rcs)
        st.range_percentiles_m = {
            "p5": float(np.percentile(rng_all, 5)),
            "p50": float(np.percentile(rng_all, 50)),
            "p95": float(np.percentile(rng_all, 95)),
            "max": float(rng_all.max()),
        }
        st.rcs_percentiles_dbsm = {f"p{q}": float(np.percentile(rcs_all, q)) for q in (5, 50, 95)}
        for name, parts in (
            ("dyn_prop_hist", dyn),
            ("invalid_state_hist", inval),
            ("ambig_state_hist", ambig),
        ):
            vals, cnt = np.unique(np.concatenate(parts), return_counts=True)
            setattr(
                st, name, {int(v): float(c / cnt.sum()) for v, c in zip(vals, cnt, strict=True)}
            )
        st.moving_fraction = float(np.concatenate(moving).mean())
        st.tangential_speed_p50_mps = float(np.median(np.concatenate(tangential)))
    if oracle:
        st.doppler_oracle_rms_p50_mps = float(np.median(oracle))
        st.doppler_oracle_rms_p95_mps = float(np.percentile(oracle, 95))
    if n_src:
        st.redetect_next = hit1 / n_src
        st.redetect_within_3 = hit3 / n_src
        st.redetect_sources = n_src
    return st


def _redetect(static_src: np.ndarray, later: list[np.ndarray]) -> tuple[int, int, int]:
    """(# re-detected in the next sweep, # within the next 3, # sources) for one sweep."""
    if len(static_src) == 0 or not later:
        return 0, 0, 0
    nxt = _has_neighbour(static_src, later[0], REDETECT_RADIUS_M)
    any3 = nxt.copy()
    for dst in later[1:REDETECT_LOOKAHEAD]:
        any3 |= _has_neighbour(static_src, dst, REDETECT_RADIUS_M)
    return int(nxt.sum()), int(any3.sum()), len(static_src)
