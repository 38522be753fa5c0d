"""The simulator's real-radar imperfections: mounting and timing errors of each unit, per-unit
sensitivity, heavy-tailed noise, dropped sweeps, and the street lining a given trajectory."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from radarslam.errors import ConfigError, DataError
from radarslam.sim.config import RadarConfig, load_sim_config
from radarslam.sim.generate import simulate
from radarslam.sim.planning import plan_logs
from radarslam.sim.radar import (
    NUSCENES_MOUNTS,
    RadarModel,
    SweepWorld,
    clock_offset_s,
    mounting_errors,
)
from radarslam.sim.truth import MeasurementTimeTruth
from radarslam.sim.world import (
    PATH_STREET_BEYOND_M,
    Boxes,
    Scatterers,
    StaticWorld,
    build_world,
    carve_corridor,
    path_street,
    street_polyline,
)

VERSION = "v1.0-mini"
SHORT = ["schedule.scenes_per_log=1", "schedule.scene_duration_s=3.0", "traffic.warmup_s=5.0"]


def _table(root: Path, name: str) -> list[dict]:
    return json.loads((root / VERSION / f"{name}.json").read_text())


def test_mounting_errors_are_seeded_per_vehicle_and_can_be_given():
    cfg = RadarConfig()
    a, b = mounting_errors(cfg, 3), mounting_errors(cfg, 3)
    assert a == b
    assert a != mounting_errors(cfg, 4)
    yaws = np.array([e.yaw_deg for e in a.values()])
    assert np.all(yaws != 0)
    given = RadarConfig(
        mounting_yaw_error_deg={"RADAR_FRONT": 1.5},
        mounting_yaw_std_deg=0.0,
        mounting_yaw_outlier_probability=0.0,
    )
    e = mounting_errors(given, 3)
    assert e["RADAR_FRONT"].yaw_deg == 1.5
    assert e["RADAR_BACK_LEFT"].yaw_deg == 0.0


def test_most_units_are_aligned_and_a_few_knocked_out():
    """Mounting yaws are a mixture: sigma 0.25 deg, and with probability 0.05 a unit drawn with
    sigma 1.5 deg instead (2,000 units: about 2.5 % beyond 1 deg, none of the aligned ones)."""
    cfg = RadarConfig()
    yaws = np.array([e.yaw_deg for s in range(400) for e in mounting_errors(cfg, s).values()])
    beyond = np.mean(np.abs(yaws) > 1.0)
    assert 0.015 < beyond < 0.04
    inner = yaws[np.abs(yaws) < 1.0]
    assert np.std(inner) == pytest.approx(0.25, rel=0.1)
    aligned = RadarConfig(mounting_yaw_outlier_probability=0.0)
    yaws = np.array([e.yaw_deg for s in range(400) for e in mounting_errors(aligned, s).values()])
    assert np.abs(yaws).max() < 5 * aligned.mounting_yaw_std_deg


def test_unknown_channel_in_radar_config_is_one_line():
    with pytest.raises(ConfigError, match=r"channel_gain_db: unknown channel 'RADAR_TOP'"):
        load_sim_config("tiny", ["radar.channel_gain_db={RADAR_TOP: -3}"])
    with pytest.raises(ConfigError, match=r"channel_clutter_scale: RADAR_FRONT must be >= 0"):
        load_sim_config("tiny", ["radar.channel_clutter_scale={RADAR_FRONT: -1}"])


def _static_world_error_m(root: Path, channel: str) -> float:
    """Median distance from each real static return, placed in the world with the written ego
    pose and calibration, to the nearest scatterer of the static world (sidecar)."""
    from scipy.spatial import cKDTree

    from radarslam.geometry import make_transform
    from radarslam.nuscenes.pcd import read_pcd

    world = np.load(root / "synthetic" / "world.npz")
    tree = cKDTree(world["scatterer_xy"])
    z = np.load(next((root / "synthetic" / "logs").glob("*.npz")))
    off = np.concatenate([[0], np.cumsum(z["n_points"])])
    sds = {r["token"]: r for r in _table(root, "sample_data")}
    poses = {r["token"]: r for r in _table(root, "ego_pose")}
    cals = {r["token"]: r for r in _table(root, "calibrated_sensor")}
    dist = []
    for i, tok in enumerate(z["sample_data_token"]):
        if str(z["channel"][i]) != channel:
            continue
        sd = sds[str(tok)]
        pts = read_pcd(root / sd["filename"])
        kind = z["point_kind"][off[i] : off[i + 1]]
        cls = z["point_class"][off[i] : off[i + 1]]
        m = (kind == 0) & (cls < 6)  # real returns of the static world (not cars)
        if not m.any():
            continue
        ep, cs = poses[sd["ego_pose_token"]], cals[sd["calibrated_sensor_token"]]
        world_from_sensor = make_transform(ep["translation"], ep["rotation"]) @ make_transform(
            cs["translation"], cs["rotation"]
        )
        p = np.column_stack([pts["x"][m], pts["y"][m], np.zeros(int(m.sum()))]).astype(float)
        xy = (p @ world_from_sensor[:3, :3].T + world_from_sensor[:3, 3])[:, :2]
        dist.append(tree.query(xy)[0])
    return float(np.median(np.concatenate(dist)))


def test_written_calibration_is_nominal_and_the_truth_is_rotated(tmp_path):
    """With a 5 deg mounting error the points are measured in the rotated (true) frame: placed
    with the written nominal calibration they land metres off the scatterers that made them."""
    base = [
        *SHORT,
        "radar.mounting_yaw_error_deg=null",
        "radar.mounting_yaw_std_deg=0",
        "radar.mounting_yaw_outlier_probability=0",
    ]
    exact = simulate("tiny", tmp_path / "exact", progress=False, overrides=base)
    rotated = simulate(
        "tiny",
        tmp_path / "rot",
        progress=False,
        overrides=[*base, "radar.mounting_yaw_error_deg={RADAR_FRONT: 5.0}"],
    )
    assert rotated.mounting_yaw_error_deg["RADAR_FRONT"] == 5.0
    assert exact.mounting_yaw_error_deg["RADAR_FRONT"] == 0.0
    summary = json.loads((tmp_path / "rot" / "synthetic" / "summary.json").read_text())
    assert summary["mounting_yaw_error_deg"]["RADAR_FRONT"] == 5.0
    cs_exact = sorted(r["rotation"] for r in _table(tmp_path / "exact", "calibrated_sensor"))
    cs_rot = sorted(r["rotation"] for r in _table(tmp_path / "rot", "calibrated_sensor"))
    assert cs_exact == cs_rot
    e_exact = _static_world_error_m(tmp_path / "exact", "RADAR_FRONT")
    e_rot = _static_world_error_m(tmp_path / "rot", "RADAR_FRONT")
    assert e_exact < 0.6
    assert e_rot > max(1.0, 2.5 * e_exact)
    # Another unit without an error stays where it was.
    assert _static_world_error_m(tmp_path / "rot", "RADAR_BACK_LEFT") < 0.6


def test_timestamp_offsets_shift_a_units_written_times(tmp_path):
    common = [*SHORT, "radar.clock_offset_mean_s=0", "radar.clock_offset_std_s=0"]
    a = simulate(
        "tiny",
        tmp_path / "a",
        progress=False,
        overrides=[*common, "radar.timestamp_offset_std_s=0"],
    )
    b = simulate(
        "tiny",
        tmp_path / "b",
        progress=False,
        overrides=[*common, "radar.timestamp_offset_std_s=0.02"],
    )
    assert all(v == 0.0 for v in a.timestamp_offset_s.values())
    for ch, dt in b.timestamp_offset_s.items():
        ta = {
            r["timestamp"]
            for r in _table(tmp_path / "a", "sample_data")
            if f"/{ch}/" in r["filename"]
        }
        tb = {
            r["timestamp"]
            for r in _table(tmp_path / "b", "sample_data")
            if f"/{ch}/" in r["filename"]
        }
        shifted = np.sort([t + round(dt * 1e6) for t in ta])
        gap = np.abs(shifted[None, :] - np.sort(list(tb))[:, None]).min(axis=1)
        # The same physical sweeps, written dt later (a chain may start one sweep apart).
        assert np.sum(gap <= 2) >= min(len(ta), len(tb)) - 2, ch
    # Every ego pose is taken at its written timestamp.
    poses = {r["token"]: r["timestamp"] for r in _table(tmp_path / "b", "ego_pose")}
    for r in _table(tmp_path / "b", "sample_data"):
        assert poses[r["ego_pose_token"]] == r["timestamp"]


def test_the_radar_clock_leads_the_pose_clock_per_log(tmp_path):
    """A log's clock offset moves every unit's written times alike; the ground-truth pose is
    taken at the written time, so it lags the measurement by the offset."""
    common = [*SHORT, "radar.timestamp_offset_std_s=0", "radar.clock_offset_std_s=0"]
    a = simulate(
        "tiny", tmp_path / "a", progress=False, overrides=[*common, "radar.clock_offset_mean_s=0"]
    )
    b = simulate(
        "tiny",
        tmp_path / "b",
        progress=False,
        overrides=[*common, "radar.clock_offset_mean_s=0.05"],
    )
    assert [log["clock_offset_s"] for log in a.per_log] == [0.0]
    assert [log["clock_offset_s"] for log in b.per_log] == [0.05]
    ta = np.sort([r["timestamp"] for r in _table(tmp_path / "a", "sample_data")])
    tb = np.sort([r["timestamp"] for r in _table(tmp_path / "b", "sample_data")])
    gap = np.abs((ta + 50_000)[None, :] - tb[:, None]).min(axis=1)
    assert np.sum(gap <= 2) >= len(tb) - 10  # a chain may start one sweep apart
    # The simulator's truth at the true measurement times: the written pose 50 ms earlier.
    truth = MeasurementTimeTruth(tmp_path / "b", VERSION)
    scene = _table(tmp_path / "b", "scene")[0]["name"]
    assert truth.clock_offset_s(scene) == 0.05
    poses = {r["token"]: r for r in _table(tmp_path / "b", "ego_pose")}
    written = [poses[r["ego_pose_token"]] for r in _table(tmp_path / "b", "sample_data")][5:50]
    stamps = np.array([p["timestamp"] for p in written])
    at_written = truth.poses(scene, stamps + 50_000)
    xy = np.array([p["translation"][:2] for p in written])
    assert np.abs(at_written[:, :2, 3] - xy).max() < 0.01
    moved = np.linalg.norm(truth.poses(scene, stamps)[:, :2, 3] - xy, axis=1)
    assert moved.max() > 0.2  # 50 ms of driving
    with pytest.raises(DataError, match="scene 'nope': not in"):
        truth.poses("nope", stamps)
    (tmp_path / "a" / VERSION / "scene.json").write_text("[")
    with pytest.raises(DataError, match=r"scene.json: corrupt JSON"):
        MeasurementTimeTruth(tmp_path / "a", VERSION)
    drawn = load_sim_config("tiny").radar
    offsets = [clock_offset_s(drawn, 3, i) for i in range(200)]
    assert np.mean(offsets) == pytest.approx(drawn.clock_offset_mean_s, abs=0.005)
    assert np.std(offsets) == pytest.approx(drawn.clock_offset_std_s, rel=0.15)


def test_front_corner_units_are_less_sensitive(tiny_dataroot):
    sds = _table(tiny_dataroot, "sample_data")
    side = next((tiny_dataroot / "synthetic" / "logs").glob("*.npz"))
    z = np.load(side)
    count = {ch: z["n_points"][z["channel"] == ch].mean() for ch in np.unique(z["channel"])}
    assert len(sds) == len(z["n_points"])
    for corner in ("RADAR_FRONT_LEFT", "RADAR_FRONT_RIGHT"):
        for full in ("RADAR_FRONT", "RADAR_BACK_LEFT", "RADAR_BACK_RIGHT"):
            assert count[corner] < 0.75 * count[full], (corner, full, count)


def _tiny_world():
    cfg = load_sim_config("tiny")
    world = build_world(cfg.city, 5)
    return cfg, world


def _sweep_residuals(cfg: RadarConfig, n: int = 40) -> np.ndarray:
    """Doppler residuals of clutter-free static returns in front of a moving sensor."""
    rng = np.random.default_rng(0)
    xs = np.linspace(10, 60, 60)
    xy = np.column_stack([np.repeat(xs, 3), np.tile([-8.0, 0.0, 8.0], len(xs))])
    m = len(xy)
    static = Scatterers(
        xy,
        np.full(m, 25.0),
        np.full(m, 1, np.int8),
        np.zeros((m, 2)),
        np.ones(m),
        np.zeros(m),
        np.ones(m),
        np.zeros(m),
    )
    world = SweepWorld(static, np.zeros((0, 4)), np.zeros((0, 4)), Boxes.empty())
    model = RadarModel(cfg)
    v_s = np.array([10.0, 0.0])
    out = []
    for _ in range(n):
        p = model.sweep(world, np.zeros(2), 0.0, v_s, rng)
        u = np.column_stack([p["x"], p["y"]]).astype(float)
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        vr = np.einsum("ij,ij->i", u, np.column_stack([p["vx"], p["vy"]]).astype(float))
        out.append(vr + u @ v_s)
    return np.concatenate(out)


def test_doppler_errors_have_heavy_tails():
    plain = RadarConfig(
        clutter_rate=0.0,
        ghost_probability=0.0,
        double_bounce_probability=0.0,
        noise={"doppler_outlier_fraction": 0.0, "velocity_quantum_mps": 0.0},
    )
    tailed = plain.model_copy(
        update={
            "noise": plain.noise.model_copy(
                update={"doppler_outlier_fraction": 0.1, "doppler_outlier_std_mps": 1.0}
            )
        }
    )
    r0, r1 = _sweep_residuals(plain), _sweep_residuals(tailed)
    # The core is the same, the tail beyond 5 sigma is not.
    assert abs(np.median(np.abs(r0)) - np.median(np.abs(r1))) < 0.03
    thr = 5 * plain.noise.doppler_std_mps
    assert np.mean(np.abs(r0) > thr) < 0.002
    assert 0.04 < np.mean(np.abs(r1) > thr) < 0.12


def test_dropped_sweeps_are_written_empty(tmp_path):
    s = simulate(
        "tiny",
        tmp_path / "d",
        progress=False,
        overrides=[*SHORT, "radar.empty_sweep_probability=0.5"],
    )
    side = next((tmp_path / "d" / "synthetic" / "logs").glob("*.npz"))
    n = np.load(side)["n_points"]
    assert len(n) == s.n_sweeps
    assert 0.35 < np.mean(n == 0) < 0.65


def test_a_given_trajectory_is_lined_with_a_street():
    cfg, world = _tiny_world()
    t = np.linspace(0, 1, 200)
    path = np.column_stack([100 + 300 * t, 150 + 30 * np.sin(3 * t)])
    lined = path_street(world, path, seed=1, keep_clear_m=3.5)
    assert isinstance(lined, StaticWorld)
    from scipy.spatial import cKDTree

    # The city is cleared off the street, parking slots included, along its whole length.
    off = cfg.city.facade_offset_m
    street, _ = street_polyline(path, step_m=1.0)
    tree = cKDTree(street)
    carved = carve_corridor(world, [street], off - 1.0)
    assert len(carved.scatterers) < len(world.scatterers)
    assert len(carved.parking.xy) < len(world.parking.xy)
    assert tree.query(carved.scatterers.xy)[0].min() > off - 1.0
    assert tree.query(carved.parking.xy)[0].min() > off - 1.0
    np.testing.assert_array_equal(
        lined.scatterers.xy[: len(carved.scatterers)], carved.scatterers.xy
    )
    new = lined.scatterers.xy[len(carved.scatterers) :]
    assert len(new) > 50
    assert cKDTree(path).query(new)[0].min() > 3.5
    # The street goes on past both ends of the drive (the radars see 100-220 m ahead).
    along_x = new[:, 0]
    assert along_x.min() < 100 - 130 and along_x.max() > 400 + 130
    d = tree.query(new)[0]
    # Facades on both sides at the street's facade offset, parking slots along the kerb.
    assert np.mean(np.abs(d - off) < 3.0) > 0.3
    slots = lined.parking.xy[len(carved.parking.xy) :]
    assert len(slots) > 0
    assert np.mean(np.abs(tree.query(slots)[0] - 4.7) < 1.0) > 0.8


def test_a_standing_ego_does_not_turn_its_street():
    # Driving 30 m along x, then standing for 10 s: the ground truth jitters by centimetres in
    # every direction, and the street must still go on along x.
    rng = np.random.default_rng(0)
    drive = np.column_stack([np.linspace(0.0, 30.0, 60), np.zeros(60)])
    stand = np.array([30.0, 0.0]) + rng.normal(0.0, 0.03, (130, 2))
    pts, s = street_polyline(np.vstack([drive, stand]), step_m=5.0)
    for part in (pts[s > s.max() - 100.0], pts[s < -10.0]):
        dx, dy = part[-1] - part[0]
        assert abs(np.degrees(np.arctan2(dy, abs(dx)))) < 1.0  # the jitter: 3 cm in 10 m
    assert pts[:, 0].max() == pytest.approx(30.0 + PATH_STREET_BEYOND_M, abs=2.0)
    assert pts[:, 0].min() == pytest.approx(-PATH_STREET_BEYOND_M, abs=0.1)
    # Standing all along: a 50 m street along x through the poses, continued as well.
    pts, s = street_polyline(np.array([5.0, 7.0]) + rng.normal(0.0, 0.03, (50, 2)), step_m=5.0)
    assert np.abs(pts[:, 1] - 7.0).max() < 0.1
    assert pts[:, 0].max() - pts[:, 0].min() == pytest.approx(50.0 + 2 * PATH_STREET_BEYOND_M)


def test_trajectory_scene_starts_at_the_first_pose():
    cfg = load_sim_config("tiny", ["schedule.scenes_per_log=1", "schedule.scene_duration_s=20"])
    (plan,) = plan_logs(cfg, duration_s=12.0)
    (start, end) = plan.scene_windows[0]
    assert start == pytest.approx(0.1)
    assert end == pytest.approx(11.8)
    free = plan_logs(cfg)[0].scene_windows[0][0]
    assert 0.5 <= free <= 3.0


def test_nuscenes_mounts_cover_every_channel():
    assert {m.channel for m in NUSCENES_MOUNTS} == set(mounting_errors(RadarConfig(), 0))


def _braking_drive_tum() -> np.ndarray:
    """25 s: 10 m/s along a gentle left curve, braking to a stop at 14 s, standing after."""
    t = np.arange(0.0, 25.0, 0.1)
    v = np.clip(10.0 - 2.5 * np.clip(t - 10.0, 0.0, None), 0.0, None)
    s = np.concatenate([[0.0], np.cumsum(0.5 * (v[1:] + v[:-1]) * 0.1)])
    yaw = 0.004 * s
    x = np.concatenate([[0.0], np.cumsum(np.cos(yaw[:-1]) * np.diff(s))])
    y = np.concatenate([[0.0], np.cumsum(np.sin(yaw[:-1]) * np.diff(s))])
    z = np.zeros_like(t)
    return np.column_stack([t, x, y, z, z, z, np.sin(yaw / 2), np.cos(yaw / 2)])


def test_cars_on_a_given_trajectorys_street_queue_with_the_ego():
    from radarslam.sim.config import TrafficConfig
    from radarslam.sim.ego import TumEgo
    from radarslam.sim.traffic import path_traffic

    ego = TumEgo(_braking_drive_tum())
    tcfg = TrafficConfig(car_density_per_km=25.0)
    traffic = path_traffic(ego.ego, ego.duration_s, tcfg, np.random.default_rng(4), 25.0)
    again = path_traffic(ego.ego, ego.duration_s, tcfg, np.random.default_rng(4), 25.0)
    n_same = len(traffic.shift_s)
    assert n_same >= 4 and len(traffic.oncoming_v) >= 4
    assert (traffic.shift_s > 0).any() and (traffic.shift_s < 0).any()  # ahead and behind
    seen_ahead_standing = 0
    for t in np.arange(0.0, 25.0, 0.25):
        boxes = traffic.boxes(float(t))
        np.testing.assert_array_equal(boxes.xy, again.boxes(float(t)).xy)
        e = ego.ego(np.array([t]))
        heading = np.array([np.cos(e.yaw[0]), np.sin(e.yaw[0])])
        rel = boxes.xy - e.xy[0]
        # Same-way cars: in the ego's lane, bumpers at least 2 m apart (the ego's 3.5 m ahead of
        # its rear axle and 0.7 m behind it; buses are 9-12 m long), never faster than the ego.
        same = slice(0, n_same)
        along = rel[same] @ heading
        half = 0.5 * boxes.length[same]
        ahead = along > 0
        assert np.all(along[ahead] - half[ahead] - 3.5 > 1.9)
        assert np.all(-along[~ahead] - half[~ahead] - 0.7 > 1.9)
        order = np.argsort(along)
        centres = np.linalg.norm(np.diff(boxes.xy[same][order], axis=0), axis=1)
        assert (centres - half[order][1:] - half[order][:-1]).min() > 1.9
        assert np.hypot(*boxes.velocity[same].T).max() <= 10.05  # the spline rings 0.1 %
        if t > 15.0:  # the ego stands: the queue ahead of it stands too
            near_ahead = (rel[same] @ heading > 0) & (np.linalg.norm(rel[same], axis=1) < 40.0)
            assert np.all(boxes.stopped[same][near_ahead])
            seen_ahead_standing += int(near_ahead.sum())
        # Oncoming cars: opposite heading, in the lane to the left of the path.
        on = slice(n_same, None)
        close = np.linalg.norm(rel[on], axis=1) < 15.0
        left = np.array([-heading[1], heading[0]])
        if np.any(close):
            np.testing.assert_allclose(rel[on][close] @ left, 3.0, atol=0.5)
            assert np.all(boxes.velocity[on][close] @ heading < -5.0)
    assert seen_ahead_standing > 0
