"""Configuration of the synthetic world generator (pydantic; YAML presets in
radarslam/configs/sim/).

Every knob that other stages use for robustness tests (traffic density, a missing radar, an empty
window, static ego, Doppler scale error, noise levels) lives here, so that a scenario is one YAML
file plus ``--set key=value`` overrides.
"""

from __future__ import annotations

from pathlib import Path

from pydantic import Field, model_validator

from radarslam.config import CONFIG_DIR, StrictModel, load_config
from radarslam.errors import ConfigError
from radarslam.types import RADAR_CHANNELS

PRESETS: tuple[str, ...] = ("tiny", "demo", "city")


class CityConfig(StrictModel):
    """The 2-D street network and what stands along it."""

    n_blocks_x: int = Field(8, ge=2, le=60)
    n_blocks_y: int = Field(6, ge=2, le=60)
    block_min_m: float = Field(80.0, gt=20)
    block_max_m: float = Field(150.0, gt=20)
    node_jitter_m: float = Field(6.0, ge=0)
    drop_edge_fraction: float = Field(0.08, ge=0, le=0.3)
    origin_m: tuple[float, float] = (300.0, 300.0)  # keeps the city in the positive map quadrant
    facade_offset_m: float = Field(12.0, gt=4)  # street centreline to facade
    facade_setback_jitter_m: float = Field(2.5, ge=0)
    building_len_min_m: float = Field(12.0, gt=2)
    building_len_max_m: float = Field(45.0, gt=2)
    gap_min_m: float = Field(2.0, ge=0)
    gap_max_m: float = Field(12.0, ge=0)
    facade_scatter_spacing_m: float = Field(2.2, gt=0.3)
    park_block_fraction: float = Field(0.12, ge=0, le=1)
    pole_spacing_m: float = Field(30.0, gt=2)
    tree_street_fraction: float = Field(0.45, ge=0, le=1)
    tree_spacing_m: float = Field(11.0, gt=2)
    guard_rail_edge_fraction: float = Field(0.12, ge=0, le=1)
    parking_edge_fraction: float = Field(0.6, ge=0, le=1)
    parking_slot_m: float = Field(6.2, gt=4)
    parking_occupancy: float = Field(0.6, ge=0, le=1)
    long_term_parked_fraction: float = Field(0.25, ge=0, le=1)  # same car every day
    map_resolution_m: float = Field(0.1, ge=0.1)

    @model_validator(mode="after")
    def _check(self) -> CityConfig:
        if self.block_max_m < self.block_min_m:
            raise ValueError("block_max_m must be >= block_min_m")
        if self.building_len_max_m < self.building_len_min_m:
            raise ValueError("building_len_max_m must be >= building_len_min_m")
        return self


class TrafficConfig(StrictModel):
    """Moving traffic: per km of street (one direction counted once per direction)."""

    car_density_per_km: float = Field(6.0, ge=0)
    cyclist_density_per_km: float = Field(0.8, ge=0)
    pedestrian_density_per_km: float = Field(5.0, ge=0)
    car_speed_mps: tuple[float, float] = (7.0, 13.0)
    cyclist_speed_mps: tuple[float, float] = (3.0, 6.0)
    pedestrian_speed_mps: tuple[float, float] = (0.9, 1.7)
    route_density_per_km: float = Field(
        0.0, ge=0
    )  # extra cars on the ego's own route, per direction (dense traffic / jams)
    signals: bool = True  # False: every light green (free-flowing dense traffic)
    # With --trajectory: cars on the path's own street too (same way: the ego's motion shifted in
    # time, as a queue; oncoming: constant speed), at car_density_per_km (+ route_density_per_km
    # same way). The city's network traffic never drives a given path.
    along_trajectory: bool = True
    light_cycle_s: tuple[float, float] = (45.0, 75.0)
    warmup_s: float = Field(60.0, ge=0)
    region_margin_m: float = Field(300.0, ge=50)


class EgoStop(StrictModel):
    """A forced static-ego window (seconds since the start of the log's drive)."""

    at_s: float = Field(ge=0)
    duration_s: float = Field(gt=0)


class EgoConfig(StrictModel):
    desired_speed_mps: tuple[float, float] = (8.5, 12.5)  # per log; capped at ~50 km/h
    max_speed_mps: float = Field(13.9, gt=0)
    max_accel_mps2: float = Field(1.6, gt=0)
    comfort_decel_mps2: float = Field(2.5, gt=0)
    max_lateral_accel_mps2: float = Field(2.0, gt=0)
    right_turn_radius_m: float = Field(8.0, gt=1)
    left_turn_radius_m: float = Field(13.0, gt=1)
    stops: list[EgoStop] = Field(default_factory=list)
    trajectory_tum: str | None = None  # drive along this TUM file instead of the street network


class RadarNoiseConfig(StrictModel):
    range_std_m: tuple[float, float] = (0.12, 0.004)  # sigma = a + b * range
    # sigma = a + b * (az / 60 deg)^2. Scan-to-map registration turns too far on this noise
    # (kiss-icp 1.001-1.007x the truth's turns with it alone, `radarslam eval`'s turn scale),
    # where on the real split's turning scenes it turns too little (0.984-0.993x).
    azimuth_std_deg: tuple[float, float] = (0.25, 1.4)
    # Radial velocity noise before the ARS408's 0.25 m/s quantisation of vx / vy: with it, the
    # Doppler residuals against a frame's joint fit match real nuScenes radar (p50 0.069 m/s,
    # p75 0.127: `python bench/realism.py`, docs/sim.md); 0.12 made them 1.65x the real ones.
    doppler_std_mps: float = Field(0.05, ge=0)
    tangential_std_mps: float = Field(0.6, ge=0)
    rcs_spread_db: float = Field(1.5, ge=0)
    # v_r measured = (1 + e) * v_r true: real ARS408 units read 0.3 % slow (docs/results.md),
    # which the odometry's doppler.speed_scale_error undoes.
    doppler_scale_error: float = Field(-0.003, ge=-0.5, le=0.5)
    position_quantum_m: float = Field(0.2, ge=0)  # ARS408 cluster DistLong/DistLat resolution
    velocity_quantum_mps: float = Field(0.25, ge=0)  # VrelLong/VrelLat resolution
    rcs_quantum_db: float = Field(0.5, ge=0)
    # Heavy tails: a share of clusters carry a much larger error (multipath inside a cluster,
    # merged targets), so a Doppler fit sees outliers among static points as on real radar.
    doppler_outlier_fraction: float = Field(0.04, ge=0, le=1)
    doppler_outlier_std_mps: float = Field(0.8, ge=0)
    azimuth_outlier_fraction: float = Field(0.05, ge=0, le=1)
    azimuth_outlier_std_deg: float = Field(4.0, ge=0)


class RadarConfig(StrictModel):
    period_s: float = Field(0.0769, gt=0.02, lt=0.5)
    period_spread_s: float = Field(0.0004, ge=0)
    jitter_s: float = Field(0.0015, ge=0)
    near_fov_deg: float = Field(60.0, gt=0, le=90)
    # The near scan's reach within +-40 deg, falling linearly to near_edge_range_m at the edge of
    # the field of view. Longer than the data sheet's 70 m: the real nuScenes units return
    # points out to 105-120 m (p99 of range) at 10-40 deg off boresight, 75-95 m at 40-60 deg,
    # and their far beam adds little (p90 of range 89-91 m within 9 deg against 98 m at 9-15
    # deg; docs/sim.md, "Range by azimuth"), hence its weaker gain.
    near_range_m: float = Field(120.0, gt=1)
    near_edge_range_m: float = Field(80.0, gt=1)
    far_fov_deg: float = Field(9.0, gt=0, le=45)
    far_range_m: float = Field(220.0, gt=1)
    near_gain_db: float = -7.0
    far_gain_db: float = -13.0
    # Two-way beam loss at the edge of the near field of view (quadratic in azimuth).
    near_rolloff_db: float = Field(10.0, ge=0)
    snr_width_db: float = Field(3.0, gt=0)
    stc_range_m: float = Field(35.0, ge=1)  # path loss is flat below this range
    max_points: int = Field(125, ge=1, le=10000)
    clutter_rate: float = Field(45.0, ge=0)  # low-quality clusters per sweep (Poisson mean)
    sidelobe_fraction: float = Field(0.2, ge=0, le=1)  # of them: sidelobe echoes of real returns
    clutter_far_fraction: float = Field(0.2, ge=0, le=1)  # of the rest: in the far beam
    ghost_probability: float = Field(0.12, ge=0, le=1)
    double_bounce_probability: float = Field(0.03, ge=0, le=1)
    noise: RadarNoiseConfig = Field(default_factory=RadarNoiseConfig)
    # Per-unit sensitivity and beam: the real side-looking front corner units return about a
    # quarter of the clusters of the front and back ones after the filters (14-16 against
    # 56-61 per sweep), weak ones (median RCS 3 against 7-7.5 dBsm), mostly near boresight: a
    # 5 dB loss (gain_biases_rcs) and a beam falling off 30 dB to the edge of the near field
    # of view (channel_near_rolloff_db) give both on the matched-path twins (docs/sim.md).
    channel_gain_db: dict[str, float] = Field(
        default_factory=lambda: {"RADAR_FRONT_LEFT": -5.0, "RADAR_FRONT_RIGHT": -5.0}
    )
    channel_clutter_scale: dict[str, float] = Field(
        default_factory=lambda: {"RADAR_FRONT_LEFT": 0.25, "RADAR_FRONT_RIGHT": 0.25}
    )
    # A unit's gain is a loss in front of its antenna (the front corner units sit behind the
    # bumper fascia): it computes RCS from received power with its nominal gain, so the RCS it
    # reports is lowered as much as its SNR (the real corner units report a median 3 dBsm
    # against 7-7.5 for the front and back units).
    gain_biases_rcs: bool = True
    # Per-unit near-beam loss at the field-of-view edge (near_rolloff_db where not given).
    channel_near_rolloff_db: dict[str, float] = Field(
        default_factory=lambda: {"RADAR_FRONT_LEFT": 30.0, "RADAR_FRONT_RIGHT": 30.0}
    )
    # The written calibrated_sensor is the nominal mounting; the simulated truth is rotated by
    # a per-unit yaw error (one vehicle: the same errors in every log). Drawn from the seed
    # unless given per channel in mounting_yaw_error_deg: most units sit within a few tenths
    # of a degree, a few are knocked out of alignment (the real split has one such car: four
    # of its five scenes integrate the Doppler yaw rate to within 4 deg over 20 s, one is 23
    # deg off).
    mounting_yaw_std_deg: float = Field(0.25, ge=0, le=10)
    mounting_yaw_outlier_probability: float = Field(0.05, ge=0, le=1)
    mounting_yaw_outlier_std_deg: float = Field(1.5, ge=0, le=10)
    mounting_yaw_error_deg: dict[str, float] | None = None
    # Per-unit constant offset of the written timestamp from the true measurement time.
    timestamp_offset_std_s: float = Field(0.005, ge=0, le=0.2)
    # Written radar timestamps are offset from the ego-pose clock by a constant drawn per log:
    # every written timestamp is the true measurement time plus it, and the ground-truth pose
    # is written at the written time. On the real scenes every method's pose at a radar
    # timestamp t fits the ground truth at t + 0-70 ms best: the radar stamps run early.
    clock_offset_mean_s: float = Field(-0.035, ge=-0.5, le=0.5)
    clock_offset_std_s: float = Field(0.025, ge=0, le=0.5)
    # A sweep that returns no cluster at all (an interrupted CAN frame list).
    empty_sweep_probability: float = Field(0.0005, ge=0, le=1)

    @model_validator(mode="after")
    def _check_channels(self) -> RadarConfig:
        for name in (
            "channel_gain_db",
            "channel_clutter_scale",
            "channel_near_rolloff_db",
            "mounting_yaw_error_deg",
        ):
            for ch in getattr(self, name) or {}:
                if ch not in RADAR_CHANNELS:
                    raise ValueError(
                        f"{name}: unknown channel {ch!r} (channels: {', '.join(RADAR_CHANNELS)})"
                    )
        for ch, v in self.channel_clutter_scale.items():
            if v < 0:
                raise ValueError(f"channel_clutter_scale: {ch} must be >= 0, got {v}")
        for ch, v in self.channel_near_rolloff_db.items():
            if v < 0:
                raise ValueError(f"channel_near_rolloff_db: {ch} must be >= 0, got {v}")
        return self


class ScheduleConfig(StrictModel):
    """Logs (drives on given days) cut into scenes."""

    n_logs: int = Field(2, ge=1, le=1000)
    n_days: int = Field(2, ge=1)  # logs fall on days drawn from this many consecutive days
    start_date: str = "2018-08-01"
    scenes_per_log: int = Field(2, ge=1, le=200)
    scene_duration_s: float = Field(20.0, gt=1)
    scene_gap_s: tuple[float, float] = (1.0, 8.0)
    sample_period_s: float = Field(0.5, gt=0.05)
    n_routes: int = Field(2, ge=1)  # canonical routes shared by logs (revisits)
    reverse_fraction: float = Field(0.4, ge=0, le=1)
    route_length_m: float = Field(1500.0, gt=100)


class TimeWindow(StrictModel):
    """[start_s, end_s) in seconds since the start of a log's drive; log index None = every log."""

    start_s: float = Field(ge=0)
    end_s: float = Field(gt=0)
    log: int | None = None


class MissingRadar(TimeWindow):
    channel: str


class ScenarioConfig(StrictModel):
    missing_radar: list[MissingRadar] = Field(default_factory=list)
    empty_windows: list[TimeWindow] = Field(default_factory=list)


class OutputConfig(StrictModel):
    version: str = "v1.0-mini"
    location: str = "synth-seaport"
    vehicle: str = "synth-ego"
    padding_bytes: tuple[int, int] = (200, 2000)


class SimConfig(StrictModel):
    name: str = "custom"
    seed: int = 0
    jobs: int = Field(1, ge=1, le=64)
    city: CityConfig = Field(default_factory=CityConfig)
    traffic: TrafficConfig = Field(default_factory=TrafficConfig)
    ego: EgoConfig = Field(default_factory=EgoConfig)
    radar: RadarConfig = Field(default_factory=RadarConfig)
    schedule: ScheduleConfig = Field(default_factory=ScheduleConfig)
    scenario: ScenarioConfig = Field(default_factory=ScenarioConfig)
    output: OutputConfig = Field(default_factory=OutputConfig)


def preset_path(name: str) -> Path:
    return CONFIG_DIR / "sim" / f"{name}.yaml"


def load_sim_config(preset_or_path: str | Path, overrides: list[str] | None = None) -> SimConfig:
    """A preset name (tiny, demo, city) or a YAML path, plus ``key.sub=value`` overrides."""
    text = str(preset_or_path)
    if text in PRESETS:
        path = preset_path(text)
    else:
        path = Path(text)
        if not path.suffix and not path.exists():
            raise ConfigError(
                f"unknown simulation preset {text!r} (presets: {', '.join(PRESETS)}; "
                "or give a YAML path)"
            )
    return load_config(SimConfig, path, overrides)
