import numpy as np
import pytest

from radarslam.place_recognition.config import REFERENCE_DPR_CHANNELS, DPRConfig
from radarslam.place_recognition.dpr import DynamicPointsRemoval, dpr_mask, make_point_mask
from radarslam.types import RADAR_DTYPE, RadarSweep


def make_sweep(v_sensor, movers_v, n_static=60, channel="RADAR_FRONT", seed=0):
    """Static points see -v_sensor; movers additionally carry their own velocity."""
    rng = np.random.default_rng(seed)
    n = n_static + len(movers_v)
    az = rng.uniform(-np.radians(60), np.radians(60), n)
    r = rng.uniform(5, 80, n)
    pts = np.zeros(n, RADAR_DTYPE)
    pts["x"], pts["y"] = r * np.cos(az), r * np.sin(az)
    vel = np.tile(-np.asarray(v_sensor, float), (n, 1))
    vel[n_static:] += np.asarray(movers_v, float).reshape(-1, 2)
    pts["vx"], pts["vy"] = vel[:, 0], vel[:, 1]
    pts["rcs"] = rng.uniform(-5, 20, n)
    pts["ambig_state"] = 3
    sweep = RadarSweep(channel, 0, pts, np.eye(4), np.eye(4))
    truth = np.r_[np.ones(n_static, bool), np.zeros(len(movers_v), bool)]
    return sweep, truth


def test_dpr_removes_movers_keeps_static_while_driving():
    # an oncoming car, a preceding faster car and a crossing cyclist-speed target
    movers = [(-9.0, 0.0), (6.0, 0.0), (0.0, 6.0), (-7.0, 2.0), (8.0, -1.0)]
    sweep, truth = make_sweep((10.0, 0.3), movers)
    keep = DynamicPointsRemoval(DPRConfig())(sweep)
    assert keep.dtype == bool and keep.shape == truth.shape
    assert keep[truth].all()
    # a mover whose Doppler is within 0.15 * |v_s| of a static point's is undetectable by design
    u = sweep.unit_directions[~truth]
    detectable = np.abs(np.einsum("ij,ij->i", u, np.array(movers))) > 0.15 * np.hypot(10, 0.3)
    assert not keep[~truth][detectable].any()
    assert detectable.sum() >= 4


def test_static_ego_rule_keeps_slow_points():
    movers = [(5.0, 0.0), (0.0, -4.0), (3.0, 3.0)]
    sweep, truth = make_sweep((0.0, 0.0), movers, n_static=20)
    keep, static, valid = dpr_mask(sweep.unit_directions, sweep.radial_velocity, DPRConfig())
    assert static and valid
    np.testing.assert_array_equal(keep, truth)


def test_channels_option_and_failures():
    sweep, _ = make_sweep((10.0, 0.0), [(-9.0, 0.0)], channel="RADAR_FRONT_LEFT")
    ref = DynamicPointsRemoval(DPRConfig.reference_three_radars())
    assert "RADAR_FRONT_LEFT" not in REFERENCE_DPR_CHANNELS
    assert ref(sweep).all()  # the reference code never filters the front-side radars
    full = DynamicPointsRemoval(DPRConfig())
    assert not full(sweep).all()
    assert full.stats.sweeps == 1 and full.stats.points_kept == 60
    # a single moving point: no velocity can be fitted; the sweep is dropped (or kept if asked)
    one, _ = make_sweep((10.0, 0.0), [], n_static=1)
    assert not DynamicPointsRemoval(DPRConfig())(one).any()
    assert DynamicPointsRemoval(DPRConfig(drop_sweep_on_failure=False))(one).all()
    empty = one.with_points(one.points[:0])
    assert DynamicPointsRemoval(DPRConfig())(empty).shape == (0,)
    assert make_point_mask(DPRConfig(enabled=False)) is None


def test_dpr_is_deterministic():
    sweep, _ = make_sweep((7.0, -1.0), [(-9.0, 0.0)] * 10, seed=4)
    a = DynamicPointsRemoval(DPRConfig())(sweep)
    b = DynamicPointsRemoval(DPRConfig())(sweep)
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("bad", [{"channels": ["RADAR_TOP"]}, {"relative_threshold": 0}])
def test_dpr_config_validation(bad):
    from radarslam.config import build_config
    from radarslam.errors import ConfigError

    with pytest.raises(ConfigError):
        build_config(DPRConfig, bad)


def test_side_radar_of_moving_car_is_not_static():
    """A side radar moving along its y axis sees broadside static points at |v_r| < 1 m/s: the
    one-radar static-ego rule trips; verification by the slow points' speed overrules it."""
    rng = np.random.default_rng(5)
    az = np.r_[rng.uniform(-0.05, 0.05, 40), rng.uniform(0.3, 1.0, 15), rng.uniform(-1.0, -0.3, 15)]
    r = rng.uniform(5, 60, len(az))
    pts = np.zeros(len(az), RADAR_DTYPE)
    pts["x"], pts["y"] = r * np.cos(az), r * np.sin(az)
    pts["vx"], pts["vy"] = 0.0, -10.0  # static world seen from a sensor moving at (0, 10)
    pts["ambig_state"] = 3
    sweep = RadarSweep("RADAR_FRONT_LEFT", 0, pts, np.eye(4), np.eye(4))
    verified = DynamicPointsRemoval(DPRConfig())(sweep)
    assert verified.all()
    paper = DynamicPointsRemoval(DPRConfig(verify_static_ego=False))(sweep)
    assert paper[:40].all() and not paper[40:].any()  # the unverified rule drops 30 static points


def test_dpr_on_simulated_sweeps(tiny_dataroot):
    """On the simulator's sweeps (truth: the sensor velocity of every sweep), DPR removes every
    clearly moving target and keeps every clearly static point while the ego drives."""
    from radarslam.nuscenes.reader import NuScenesRadar

    side = np.load(next((tiny_dataroot / "synthetic" / "logs").glob("*.npz")))
    v_true = dict(zip(side["sample_data_token"], side["v_sensor"], strict=True))
    reader = NuScenesRadar(tiny_dataroot, "v1.0-mini")
    dpr = DynamicPointsRemoval(DPRConfig())
    movers = removed = static = kept = 0
    for channel in ("RADAR_FRONT", "RADAR_FRONT_LEFT", "RADAR_BACK_RIGHT"):
        for sweep in reader.iter_sweeps(reader.scenes()[0], channel):
            v = v_true[sweep.token]
            if len(sweep) == 0 or np.linalg.norm(v) < 1.0:
                continue
            keep = dpr(sweep)
            residual = np.abs(sweep.radial_velocity + sweep.unit_directions @ v)
            movers += int((residual > 1.5).sum())
            removed += int((~keep[residual > 1.5]).sum())
            static += int((residual < 0.3).sum())
            kept += int(keep[residual < 0.3].sum())
    assert movers > 100 and static > 5000
    assert removed / movers >= 0.99
    assert kept / static >= 0.99
