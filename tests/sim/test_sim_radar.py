"""Unit tests of the ARS408 model on hand-made worlds: visibility, specularity, knobs, fields."""

from __future__ import annotations

import numpy as np
import pytest

from radarslam.sim.config import RadarConfig
from radarslam.sim.radar import NUSCENES_MOUNTS, RadarModel, SweepWorld, rms_code
from radarslam.sim.world import GUARDRAIL, MOVING_CAR, POLE, Boxes, Scatterers, _make


def _quiet(**noise) -> RadarConfig:
    """No clutter or ghosts; optional noise overrides."""
    cfg = RadarConfig(clutter_rate=0.0, ghost_probability=0.0, double_bounce_probability=0.0)
    return cfg.model_copy(update={"noise": cfg.noise.model_copy(update=noise)})


def _world(sc: Scatterers, occ=None, boxes=None) -> SweepWorld:
    occ = np.zeros((0, 4)) if occ is None else np.asarray(occ, float)
    return SweepWorld(sc, occ, occ, Boxes.empty() if boxes is None else boxes)


def _detect_rate(model, world, n=200, v_s=(5.0, 0.0)):
    rng = np.random.default_rng(0)
    return np.mean(
        [len(model.sweep(world, np.zeros(2), 0.0, np.array(v_s), rng)) for _ in range(n)]
    )


def test_occlusion_by_a_wall():
    pole = _make([[30.0, 0.0]], 10.0, POLE)
    model = RadarModel(_quiet())
    assert _detect_rate(model, _world(pole)) > 0.9
    wall = [[15.0, -5.0, 15.0, 5.0]]
    assert _detect_rate(model, _world(pole, wall)) == 0.0
    side_wall = [[15.0, 5.0, 15.0, 15.0]]  # not on the line of sight
    assert _detect_rate(model, _world(pole, side_wall)) > 0.9


def test_guard_rail_is_specular():
    # 30 deg off boresight (near scan only), 40 m away.
    u = np.array([np.cos(np.deg2rad(30)), np.sin(np.deg2rad(30))])
    model = RadarModel(_quiet())

    def rail(tilt):
        c, s = np.cos(tilt), np.sin(tilt)
        normal = -np.array([[c * u[0] - s * u[1], s * u[0] + c * u[1]]])
        return _make([40.0 * u], -10.0, GUARDRAIL, normal, lobe=np.deg2rad(3.5), spec=26.0)

    assert _detect_rate(model, _world(rail(0.0))) > 0.8  # seen perpendicular: a mirror flash
    assert _detect_rate(model, _world(rail(0.6))) < 0.3  # 34 deg off: diffuse part only


def test_fov_and_range_limits():
    model = RadarModel(_quiet())
    behind = _make([[-20.0, 0.0]], 15.0, POLE)
    outside = _make([[10.0, 30.0]], 15.0, POLE)  # 72 deg off boresight
    # 29 deg off boresight: within the near scan's reach (120 m) at 100 m, beyond it at 130 m
    near_side = _make([[100.0 * np.cos(0.5), 100.0 * np.sin(0.5)]], 15.0, POLE)
    far_side = _make([[130.0 * np.cos(0.5), 130.0 * np.sin(0.5)]], 15.0, POLE)
    far_bore = _make([[130.0, 0.0]], 22.0, POLE)  # beyond the near scan, in the far beam
    edge = _make([[90.0 * np.cos(1.0), 90.0 * np.sin(1.0)]], 15.0, POLE)  # 57 deg: reach 80 m
    assert _detect_rate(model, _world(behind), 50) == 0
    assert _detect_rate(model, _world(outside), 50) == 0
    assert _detect_rate(model, _world(far_side), 50) == 0
    assert _detect_rate(model, _world(edge), 50) == 0
    assert _detect_rate(model, _world(near_side), 100) > 0.3
    assert _detect_rate(model, _world(far_bore), 100) > 0.5  # far scan on boresight


@pytest.mark.parametrize("scale", [0.0, 0.05])
def test_doppler_scale_error_and_exact_compensation(scale):
    rng = np.random.default_rng(1)
    xy = np.column_stack([rng.uniform(5, 60, 300), rng.uniform(-30, 30, 300)])
    sc = _make(xy, 12.0, POLE)
    model = RadarModel(
        _quiet(
            doppler_std_mps=0.0,
            tangential_std_mps=0.0,
            velocity_quantum_mps=0.0,
            doppler_scale_error=scale,
            doppler_outlier_fraction=0.0,
        )
    )
    v_s = np.array([8.0, 0.5])
    pts = model.sweep(_world(sc), np.zeros(2), 0.0, v_s, rng)
    assert len(pts) > 50
    xyp = np.column_stack([pts["x"], pts["y"]]).astype(float)
    u = xyp / np.linalg.norm(xyp, axis=1, keepdims=True)
    vc = np.column_stack([pts["vx_comp"], pts["vy_comp"]]).astype(float)
    # Static world: compensated radial velocity = -scale * u.v_sensor (0 without scale error).
    np.testing.assert_allclose(u[:, 0] * vc[:, 0] + u[:, 1] * vc[:, 1], -scale * (u @ v_s),
                               atol=2e-5)  # fmt: skip
    v = np.column_stack([pts["vx"], pts["vy"]]).astype(float)
    np.testing.assert_allclose(np.einsum("ij,ij->i", u, v - vc), -(u @ v_s), atol=2e-5)


def test_moving_car_is_an_extended_moving_target():
    car = Boxes(np.array([[25.0, 1.0]]), np.array([0.0]), np.array([4.6]), np.array([1.9]),
                np.array([[-8.0, 0.0]]), np.array([MOVING_CAR], np.int8), np.array([False]),
                np.array([1]))  # fmt: skip
    model = RadarModel(_quiet())
    rng = np.random.default_rng(2)
    counts, dyn = [], []
    for _ in range(60):
        pts = model.sweep(_world(Scatterers.empty(), boxes=car), np.zeros(2), 0.0,
                          np.array([5.0, 0.0]), rng)  # fmt: skip
        counts.append(len(pts))
        dyn.extend(pts["dyn_prop"].tolist())
    assert np.mean(counts) > 1.5  # several clusters on one car
    assert max(counts) <= 8  # but only its visible side
    assert np.mean(np.isin(dyn, [0, 2, 6])) > 0.9  # oncoming car: moving classes


def test_cluster_cap_and_clutter_quality():
    model = RadarModel(RadarConfig(clutter_rate=300.0))
    pts = model.sweep(_world(Scatterers.empty()), np.zeros(2), 0.0, np.zeros(2),
                      np.random.default_rng(3))  # fmt: skip
    assert len(pts) == 125
    assert np.mean(pts["invalid_state"] != 0) > 0.4
    assert np.array_equal(pts["id"], np.arange(125))
    r = np.hypot(pts["x"], pts["y"])
    assert np.all(np.diff(r) >= -1e-3)  # sorted by range


def test_rms_code_and_mounts():
    assert rms_code(np.array([0.004]))[0] == 0
    assert rms_code(np.array([0.1]))[0] == 12
    assert rms_code(np.array([100.0]))[0] == 30
    front = NUSCENES_MOUNTS[0].ego_from_sensor()
    np.testing.assert_allclose(front[:3, 3], [3.412, 0.0, 0.5])
    left = NUSCENES_MOUNTS[1].ego_from_sensor()
    assert np.rad2deg(np.arctan2(left[1, 0], left[0, 0])) == pytest.approx(88.3)


def test_mount_rotation_matches_scipy_euler():
    from scipy.spatial.transform import Rotation

    from radarslam.sim.radar import RadarMount

    m = RadarMount("RADAR_X", 1.0, 2.0, 0.5, 30.0, 1.5, -2.0)
    want = Rotation.from_euler("xyz", [1.5, -2.0, 30.0], degrees=True).as_matrix()
    np.testing.assert_allclose(m.ego_from_sensor()[:3, :3], want, atol=1e-12)


def _pole_at(range_m: float, az_deg: float, rcs: float):
    a = np.deg2rad(az_deg)
    return _make([[range_m * np.cos(a), range_m * np.sin(a)]], rcs, POLE)


def test_front_corner_units_lose_gain_and_report_it_in_their_rcs():
    """The corner units' 5 dB loss lowers their SNR and, as a unit computing RCS with its
    nominal gain does, the RCS they report; the front unit sees the same pole at its RCS."""
    cfg = _quiet(rcs_spread_db=0.0, rcs_quantum_db=0.0)
    front, corner = RadarModel(cfg, "RADAR_FRONT"), RadarModel(cfg, "RADAR_FRONT_LEFT")
    world = _world(_pole_at(20.0, 0.0, 20.0))
    rng = np.random.default_rng(0)
    v = np.array([5.0, 0.0])
    rcs_front = [
        float(p) for _ in range(20) for p in front.sweep(world, np.zeros(2), 0, v, rng)["rcs"]
    ]
    rcs_corner = [
        float(p) for _ in range(20) for p in corner.sweep(world, np.zeros(2), 0, v, rng)["rcs"]
    ]
    assert rcs_front and rcs_corner
    assert np.median(rcs_front) - np.median(rcs_corner) == pytest.approx(5.0, abs=0.01)
    unbiased = RadarModel(cfg.model_copy(update={"gain_biases_rcs": False}), "RADAR_FRONT_LEFT")
    rcs = [
        float(p) for _ in range(20) for p in unbiased.sweep(world, np.zeros(2), 0, v, rng)["rcs"]
    ]
    assert np.median(rcs) == pytest.approx(np.median(rcs_front), abs=0.01)


def test_front_corner_units_have_a_narrower_near_beam():
    """A weak pole 50 deg off boresight at 30 m: seen by the front unit most of the time, hardly
    by a corner unit (30 dB of loss at the near scan's edge instead of 10); on boresight both
    see it."""
    cfg = _quiet()
    front, corner = RadarModel(cfg, "RADAR_FRONT"), RadarModel(cfg, "RADAR_FRONT_LEFT")
    off = _world(_pole_at(30.0, 50.0, 5.0))
    on = _world(_pole_at(30.0, 0.0, 5.0))
    assert _detect_rate(front, off) > 0.8
    assert _detect_rate(corner, off) < 0.2
    assert _detect_rate(front, on) > 0.8 and _detect_rate(corner, on) > 0.8
    wide = RadarModel(cfg.model_copy(update={"channel_near_rolloff_db": {}}), "RADAR_FRONT_LEFT")
    assert _detect_rate(wide, off) > 0.5  # the same 5 dB loss with the common beam
