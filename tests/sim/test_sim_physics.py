"""Physics and statistics of the synthetic radar: Doppler oracle, ground truth, realism bands."""

from __future__ import annotations

import json
from collections import defaultdict

import numpy as np
import pytest

from radarslam.geometry import make_transform
from radarslam.nuscenes.pcd import read_pcd
from radarslam.sim.config import load_sim_config
from radarslam.sim.ego import canonical_routes, extend_route
from radarslam.sim.generate import _world_for
from radarslam.sim.traffic import simulate_traffic
from radarslam.sim.world import build_world, parked_cars

VERSION = "v1.0-mini"


@pytest.fixture(scope="module")
def sweeps(tiny_dataroot):
    """All sweeps of the tiny dataroot with their sidecar truth, grouped by channel."""
    root = tiny_dataroot
    sds = json.loads((root / VERSION / "sample_data.json").read_text())
    side = np.load(next((root / "synthetic" / "logs").glob("*.npz")))
    v_true = dict(zip(side["sample_data_token"].tolist(), side["v_sensor"], strict=True))
    out = []
    for r in sds:
        out.append((r, read_pcd(root / r["filename"]), v_true[r["token"]]))
    return out


def _u(p):
    xy = np.column_stack([p["x"], p["y"]]).astype(np.float64)
    return xy / np.linalg.norm(xy, axis=1, keepdims=True)


def test_doppler_oracle_holds_exactly_per_sweep(sweeps):
    worst, worst_fit = 0.0, 0.0
    for _, p, v_s in sweeps:
        if len(p) < 3:
            continue
        u = _u(p)
        v = np.column_stack([p["vx"], p["vy"]]).astype(np.float64)
        vc = np.column_stack([p["vx_comp"], p["vy_comp"]]).astype(np.float64)
        lhs = np.einsum("ij,ij->i", u, v - vc)
        # One sensor velocity per sweep explains every point (least squares, then residual).
        fit, *_ = np.linalg.lstsq(-u, lhs, rcond=None)
        worst = max(worst, float(np.abs(lhs + u @ fit).max()))
        worst_fit = max(worst_fit, float(np.abs(fit - v_s).max()))
        # v_comp is purely radial.
        cross = u[:, 0] * vc[:, 1] - u[:, 1] * vc[:, 0]
        assert np.abs(cross).max() < 1e-4
    assert worst < 2e-4
    assert worst_fit < 2e-4  # ... and it is the true sensor velocity over ground


def test_raw_velocity_has_a_tangential_part(sweeps):
    tang = []
    for _, p, v_s in sweeps:
        if np.linalg.norm(v_s) < 2.0:
            continue
        u = _u(p)
        tang.append(np.abs(u[:, 0] * p["vy"] - u[:, 1] * p["vx"]))
    tang = np.concatenate(tang)
    assert 1.0 < np.median(tang) < 6.0


def test_ground_truth_pose_is_consistent_with_the_doppler_velocity(tiny_dataroot, sweeps):
    """Central differences of ego_pose reproduce the sensor velocity the Doppler encodes, once
    the unit's true mounting yaw error (reported in summary.json) is taken into account."""
    root = tiny_dataroot
    yaw_err = json.loads((root / "synthetic" / "summary.json").read_text())[
        "mounting_yaw_error_deg"
    ]
    poses = {p["token"]: p for p in json.loads((root / VERSION / "ego_pose.json").read_text())}
    cal = {
        c["token"]: c for c in json.loads((root / VERSION / "calibrated_sensor.json").read_text())
    }
    chains = defaultdict(list)
    for r, _, v_s in sweeps:
        chains[(r["calibrated_sensor_token"], r["filename"].split("__")[0][:7])].append((r, v_s))
    errs = []
    for (cs_tok, _), items in chains.items():
        items.sort(key=lambda x: x[0]["timestamp"])
        c = cal[cs_tok]
        e_s = make_transform(c["translation"], c["rotation"])
        t = np.array([r["timestamp"] for r, _ in items]) * 1e-6
        w_s = []
        for r, _ in items:
            p = poses[r["ego_pose_token"]]
            w_s.append(make_transform(p["translation"], p["rotation"]) @ e_s)
        w_s = np.array(w_s)
        for k in range(1, len(items) - 1):
            if t[k + 1] - t[k - 1] > 0.2:  # gap between scenes
                continue
            v_w = (w_s[k + 1, :2, 3] - w_s[k - 1, :2, 3]) / (t[k + 1] - t[k - 1])
            v_nominal = w_s[k, :2, :2].T @ v_w
            # The sidecar's velocity is in the true (rotated) sensor frame.
            a = np.deg2rad(yaw_err[items[k][0]["filename"].split("/")[1]])
            v_true = np.array([[np.cos(a), np.sin(a)], [-np.sin(a), np.cos(a)]]) @ v_nominal
            errs.append(np.linalg.norm(v_true - items[k][1]))
    errs = np.array(errs)
    assert len(errs) > 500
    assert np.median(errs) < 0.03 and errs.max() < 0.3


def test_statistics_in_realistic_bands(sweeps):
    """Bands around the same figures on the real nuScenes mini radar scenes: 41 % of sweeps at
    the 125-cluster cap, median range 44 m, RCS 5/50/95 % = -4 / 4 / 20 dBsm, invalid_state 0:
    52 %, ambig_state 3: 84 %, default filters keep 48 %."""
    n = np.array([len(p) for _, p, _ in sweeps])
    assert n.max() <= 125
    assert 0.15 < np.mean(n == 125) < 0.6
    pts = np.concatenate([p for _, p, _ in sweeps])
    r = np.hypot(pts["x"], pts["y"])
    assert 30 < np.median(r) < 60
    assert 90 < r.max() < 230
    p5, p50, p95 = np.percentile(pts["rcs"], [5, 50, 95])
    assert -9 < p5 < -2 and 1 < p50 < 8 and 11 < p95 < 24
    inv0 = np.mean(pts["invalid_state"] == 0)
    amb3 = np.mean(pts["ambig_state"] == 3)
    assert 0.48 < inv0 < 0.68 and 0.8 < amb3 < 0.98
    passed = (pts["invalid_state"] == 0) & (pts["dyn_prop"] <= 6) & (pts["ambig_state"] == 3)
    assert 0.38 < passed.mean() < 0.65
    dp = np.bincount(pts["dyn_prop"], minlength=8) / len(pts)
    assert dp[1] + dp[3] > 0.6  # mostly stationary / stationary candidate
    assert dp[0] + dp[2] + dp[6] > 0.02  # moving traffic
    # Positions on the ARS408 0.2 m grid, z = 0, ids 0..n-1 per sweep.
    assert np.allclose(np.round(pts["x"] / 0.2) * 0.2, pts["x"], atol=1e-4)
    assert np.all(pts["z"] == 0)
    for _, p, _ in sweeps[:20]:
        assert np.array_equal(p["id"], np.arange(len(p)))


def test_parked_cars_change_between_days_but_partly_stay():
    cfg = load_sim_config("tiny")
    world = build_world(cfg.city, cfg.seed)
    a = parked_cars(world, day=0, seed=cfg.seed)
    b = parked_cars(world, day=1, seed=cfg.seed)
    a2 = parked_cars(world, day=0, seed=cfg.seed)
    np.testing.assert_array_equal(a.xy, a2.xy)
    slots_a = set((a.obj_id % 1_000_000).tolist())
    slots_b = set((b.obj_id % 1_000_000).tolist())
    n_slots = len(world.parking.xy)
    assert n_slots > 40
    jacc = len(slots_a & slots_b) / len(slots_a | slots_b)
    assert 0.2 < jacc < 0.85  # some cars stay (long-term), many change
    assert 0.3 * n_slots < len(slots_a) < 0.9 * n_slots


def test_ego_stops_at_red_lights_and_forced_stops():
    cfg = load_sim_config("tiny", ["ego.stops=[{at_s: 20.0, duration_s: 12.0}]"])
    world, _ = _world_for(cfg)
    rng = np.random.default_rng(3)
    route = canonical_routes(world.network, np.random.default_rng(5), 1, 600.0)[0]
    route = extend_route(world.network, rng, route, 3000.0)
    sim = simulate_traffic(
        world.network, cfg.traffic, cfg.ego, rng, 240.0, route, 10.0, 11.0, 10.0, world.bounds
    )
    t = np.arange(0.0, 240.0, 0.1)
    ego = sim.ego(t)
    v = ego.v_fwd_mps
    still = v < 0.05
    # Lengths of static-ego periods.
    edges = np.flatnonzero(np.diff(np.concatenate([[0], still.astype(int), [0]])))
    runs = (edges[1::2] - edges[::2]) * 0.1
    assert still[(t > 25.5) & (t < 31.9)].all()  # the forced stop (after braking)
    assert np.any((runs >= 5.0) & (runs <= 40.0))
    assert len(runs) >= 2  # plus at least one red light
    assert v.max() < 14.0 and 3.0 < v.mean() < 10.0
    assert np.abs(ego.yaw_rate_radps).max() < 0.8  # bicycle-like yaw-rate limit
    boxes = sim.boxes(100.0)
    speeds = np.linalg.norm(boxes.velocity, axis=1)
    assert (speeds > 3).sum() > 5 and boxes.stopped.sum() >= 1


def test_sidecar_point_labels_match_the_points(tiny_dataroot, sweeps):
    side = np.load(next((tiny_dataroot / "synthetic" / "logs").glob("*.npz")))
    n = side["n_points"]
    assert n.sum() == len(side["point_class"]) == sum(len(p) for _, p, _ in sweeps)
    off = dict(zip(side["sample_data_token"].tolist(), np.cumsum(n) - n, strict=True))
    static_vr, moving_vr, kinds = [], [], []
    for r, p, _ in sweeps:
        o = off[r["token"]]
        cls = side["point_class"][o : o + len(p)]
        kind = side["point_kind"][o : o + len(p)]
        speed = side["point_ground_speed_mps"][o : o + len(p)]
        u = _u(p)
        vr = np.abs(u[:, 0] * p["vx_comp"] + u[:, 1] * p["vy_comp"])
        real = kind <= 1
        static_vr.append(vr[real & (speed < 0.05)])
        moving_vr.append(vr[real & (speed > 3.0) & np.isin(cls, [7, 8])])
        kinds.append(kind)
    static_vr, moving_vr = np.concatenate(static_vr), np.concatenate(moving_vr)
    kinds = np.bincount(np.concatenate(kinds), minlength=7) / sum(len(k) for k in kinds)
    # Static world: compensated Doppler is noise only; moving cars/cyclists: mostly clearly moving.
    assert np.percentile(static_vr, 95) < 0.5
    assert len(moving_vr) > 50 and np.median(moving_vr) > 1.0
    assert 0.45 < kinds[0] + kinds[1] < 0.75  # real detections
    assert kinds[2] + kinds[3] > 0.003  # multipath ghosts exist
    assert 0.2 < kinds[4] + kinds[5] + kinds[6] < 0.5  # clutter and sidelobe clusters
    assert kinds[6] > 0.05  # sidelobe echoes of real returns
