"""The SLAM preset (``radarslam/configs/slam/<preset>.yaml``): front end, loop detection, back
end."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator

from radarslam.config import StrictModel
from radarslam.odometry.config import OdometryConfig
from radarslam.slam.backend_config import BackendConfig
from radarslam.types import check_radar_channel


class KeyFrameConfig(StrictModel):
    #: Sweeps per radar accumulated into a key frame's cloud (AutoPlace: 7, about 0.5 s).
    nsweeps: int = Field(7, ge=1, le=30)
    ref_channel: str = "RADAR_FRONT"
    min_distance_m: float = Field(1.0, ge=0.0)
    #: Key-frame gate: a nuScenes key frame (sample) becomes a SLAM key frame only once the
    #: vehicle has moved ``min_travel_m`` or turned ``min_turn_deg`` since the previous one, or
    #: ``max_interval_s`` (None: never) has passed. The motion and covariance between two key
    #: frames cover the samples passed over. 0: every sample is a key frame (a gate is faster,
    #: but links fewer sessions: key frames taken while standing are new looks at a place).
    min_travel_m: float = Field(0.0, ge=0.0)
    min_turn_deg: float = Field(5.0, gt=0.0)
    max_interval_s: float | None = Field(2.0, gt=0.0)
    #: A verification local map is the key frame's cloud plus this many neighbours on each side
    #: (only past ones for the query, which has no future yet), placed with odometry.
    local_map_neighbors: int = Field(4, ge=0, le=50)
    #: Which dynamic-point removal cleans the key-frame clouds: the odometry's joint Doppler fit
    #: of every frame (free: it is already computed) or AutoPlace's DPR run again per sweep
    #: (Algorithm 1 of the paper, as the place-recognition training data was made).
    dynamic_points: Literal["odometry", "dpr"] = "odometry"
    #: The radars' mounting yaws the key-frame clouds are built with: ``configured`` (the
    #: configuration's ``odometry.mounting_yaw_deg``) or ``applied`` (what the odometry applies
    #: from the run's first frame: those plus a calibration pass's estimate). Either is the same
    #: for every session; the odometry's own per-session estimate never turns a cloud. With
    #: ``applied`` loops between streets driven opposite ways lose their lateral bias (0.10-0.25 m
    #: down to 0.01-0.08 m on the synthetic runs) but the maps come out no better (docs/results.md).
    cloud_calibration: Literal["configured", "applied"] = "configured"

    _v_ref = field_validator("ref_channel")(check_radar_channel)


class LoopDetectionConfig(StrictModel):
    enabled: bool = True
    #: AutoPlace checkpoint; None = the compact model shipped with the package.
    checkpoint: str | None = None
    #: Place-recognizer preset (accumulation / DPR / image / RCSHR settings) matching the model.
    recognizer_config: str | None = "place_recognition/recognizer_default.yaml"
    num_candidates: int = Field(3, ge=1, le=50)
    #: Candidates farther than this in descriptor space (unit vectors: 0..2) are not verified:
    #: each one verified costs a registration search. None: verify every candidate.
    max_descriptor_distance: float | None = Field(0.85, gt=0.0)
    #: Key frames of the same session closer in time than this are never candidates.
    exclude_recent_s: float = Field(30.0, ge=0.0)
    #: After an accepted loop, the next this-many key frames of the session skip loop search.
    min_key_frames_between_loops: int = Field(4, ge=0)
    #: When odometry (same session) or the map (both sessions placed) predicts the relative pose,
    #: verification searches only this far around the prediction, at its heading: ~4x cheaper
    #: than the global search, and a false match elsewhere cannot be accepted.
    guided_search_radius_m: float = Field(8.0, gt=0.0)
    #: Proximity search: a key frame whose group (the map, or sessions linked to each other)
    #: already holds key frames within this radius of its predicted pose is registered against
    #: the nearest of them, guided by the prediction, without waiting for place recognition.
    #: This is what keeps loop closures coming at every key frame of a revisit once a session is
    #: linked; place recognition is what links it. None: off.
    proximity_radius_m: float | None = Field(10.0, gt=0.0)
    #: Proximity candidates verified per key frame (nearest first, one per other session).
    proximity_candidates: int = Field(1, ge=1, le=10)
    #: Proximity verification starts from the map's prediction, so it looks only at points
    #: within this range (None: all) and uses a lower tight-fitness threshold than the global
    #: search.
    proximity_max_range_m: float | None = Field(60.0, gt=0.0)
    proximity_min_tight_fitness: float = Field(0.08, ge=0.0, le=1.0)
    #: Between two sessions already in the map, a verified loop that moves the query farther than
    #: this from where the map predicts it is rejected (a look-alike street, not a revisit).
    map_consistency_m: float = Field(3.0, gt=0.0)
    map_consistency_deg: float = Field(10.0, gt=0.0)
    #: The same test, tighter, for proximity loops: their prediction chains from a recent loop
    #: over a short span of odometry (correct proximity loops land within 0.5 m of it in 99 %
    #: of cases on the synthetic benchmark and seed 7), so a registration that moved the query
    #: farther than this has slid along a street. None: ``map_consistency_m``.
    proximity_consistency_m: float | None = Field(1.5, gt=0.0)
    #: A session not yet in the map verifies at most this many candidates per key frame (each
    #: needs the costly global search over headings and translations).
    unlinked_candidates_per_key_frame: int = Field(1, ge=1)
    #: Turned AutoPlace candidates, for streets a session drives the other way round from the
    #: map. AutoPlace's image is drawn in the vehicle's frame, so its own query rarely proposes
    #: them. Every ``reversed_every``-th key frame of a session outside the map that closed
    #: nothing else queries the key frames of sessions not linked to it yet (not only the
    #: map's: a street is often driven the other way by a session that joins the map later)
    #: with its image sequence turned by 180 deg; the best match goes to the translation search
    #: over headings within ``reversed_heading_range_deg`` of a half turn, then to the usual
    #: tests and session linking. False: off.
    reversed_search: bool = True
    reversed_every: int = Field(6, ge=1)
    reversed_heading_range_deg: float = Field(60.0, gt=0, le=360)
    #: Map merging. Once a session closes loops in its own group, recognition stops looking
    #: beyond it: its best matches are the group's other passes of the same street, and the
    #: proximity loops that then close every key frame hold recognition off
    #: (``min_key_frames_between_loops``). So every ``merge_search_every``-th key frame of a
    #: session, while other groups exist, AutoPlace is also queried among the key frames of the
    #: other groups only, with the key frame's images as they are and turned by 180 deg (with
    #: ``reversed_search``), whatever closed the key frame; the best match of each query goes to
    #: the global search (within ``max_descriptor_distance`` for the plain one) and, accepted, is
    #: a vote between the two groups. None: off. With 6 it joins groups the default leaves
    #: apart (the city subset's map: 3 of 32 sessions -> 11) but also lets a look-alike
    #: street link a session at the wrong place on another city (docs/results.md, settings
    #: table).
    merge_search_every: int | None = Field(None, ge=1)
    #: The merge search's best match among the other groups is there whether they hold the
    #: place or not, so its registrations must pass this ``min_tight_fitness`` (measured at
    #: 0.15 when the verifier's was 0.12; docs/results.md, settings table).
    merge_min_tight_fitness: float = Field(0.15, ge=0.0, le=1.0)
    #: A new session joins the map only after this many loops agree on where it is: placed by
    #: each loop, the loops' key frames land within ``link_consistency_m`` of each other (and
    #: the headings within ``link_consistency_deg``). Along a straight street the global search
    #: can align a look-alike stretch metres off with good fitness, and proximity loops would
    #: inherit the offset.
    link_min_consistent_loops: int = Field(2, ge=1)
    link_consistency_m: float = Field(1.5, gt=0.0)
    link_consistency_deg: float = Field(10.0, gt=0.0)
    #: Two scenes of one log are one vehicle's drive: a link may not put the later scene's first
    #: key frame farther from the earlier one's last than this speed over the time between them
    #: (plus 20 m of odometry drift). Look-alike parallel streets hundreds of metres apart then
    #: cannot take a session of the same drive. None: off.
    same_log_max_speed_mps: float | None = Field(30.0, gt=0.0)


def _slam_odometry() -> OdometryConfig:
    """The odometry of a SLAM run: the odometry's defaults with a calibration pass (a run of
    many sessions of one vehicle converges on its mounting yaws; on the synthetic long-scene
    benchmark and seeds 7, 11 and 21 the odometry's joint ATE falls 25-55 %), over every frame
    (``calibration_pass_max_sigma_deg`` ends it early instead), the yaws observed through the
    registration only (the Doppler residuals as well move the synthetic maps by up to 0.2 m
    either way: docs/results.md, settings table), and the pass's estimate applied as the filter
    leaves it (``common_yaw: filter``: with ``median`` seeds 7 and 21 lose 0.09 and 0.06 m,
    seed 11 gains 0.04 m, the same sessions everywhere; docs/results.md, settings table)."""
    cfg = OdometryConfig()
    cfg.fusion.calibration.passes = 2
    cfg.fusion.calibration.pass_frame_stride = 1
    cfg.fusion.calibration.residual_cov_scale = None
    cfg.fusion.calibration.common_yaw = "filter"
    return cfg


class SlamConfig(StrictModel):
    odometry: OdometryConfig = Field(default_factory=_slam_odometry)
    key_frames: KeyFrameConfig = Field(default_factory=KeyFrameConfig)
    loops: LoopDetectionConfig = Field(default_factory=LoopDetectionConfig)
    backend: BackendConfig = Field(default_factory=BackendConfig)
    #: Where the session processed first starts: its first ground-truth pose (the map lives in the
    #: nuScenes global frame; no other ground truth is used) or the identity. Later sessions
    #: always start unknown and are placed by loop closures.
    first_session_anchor: Literal["ground_truth", "identity"] = "ground_truth"
    #: A scene that starts within the odometry's ``fusion.max_gap_s`` of the end of the scene
    #: processed just before it, cut from the same log (one drive), continues that scene's
    #: odometry instead of starting unknown: the vehicle drove on through the gap, so the two
    #: sessions are one chain in the pose graph, tied by the odometry's key-frame motion across
    #: the gap. Consecutive nuScenes scenes may share their boundary key frame; it is driven
    #: once. False: every scene is its own chain, placed only by loops.
    continue_log_scenes: bool = True
    #: With ``odometry.fusion.calibration.passes: 2`` the odometry first runs over the scenes,
    #: in order, to estimate the vehicle's mounting yaws; it stops after the scene at which every
    #: yaw's sigma is below this (deg), so a run of many scenes pays for the few it takes to
    #: converge, and the run applies the estimate from its first frame only if it got there
    #: (None: every scene, applied in any case). From the second scene on the pass also gives
    #: up once the scenes left could not get there
    #: (``calibration_pass.PASS_PROJECTION_SLACK``): the demo's six 20 s scenes stop after two.
    calibration_pass_max_sigma_deg: float | None = Field(0.1, gt=0.0)
    #: Run the odometry (reading, Doppler, kiss-icp, key-frame clouds) in a forked process while
    #: this one does the key-frame work (recognition, registration, iSAM2): on two cores the two
    #: overlap. Identical results, since odometry never depends on loops. Ignored where the
    #: platform cannot fork. False: everything in the calling process.
    pipelined: bool = True
