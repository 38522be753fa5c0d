"""bench/realism.py: the twin of the real car gets the mounting yaws ours estimates on its scene."""

import importlib.util
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


@pytest.fixture
def realism(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))  # its sibling helpers (_cli)
    spec = importlib.util.spec_from_file_location("bench_realism", BENCH / "realism.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_the_twin_of_the_car_carries_the_estimated_mounting_yaws(realism):
    from radarslam.sim.config import load_sim_config
    from radarslam.sim.radar import mounting_errors

    estimate = {
        "RADAR_FRONT": -0.3217,
        "RADAR_FRONT_LEFT": 1.1391,
        "RADAR_FRONT_RIGHT": 0.3,
        "RADAR_BACK_LEFT": 1.2844,
        "RADAR_BACK_RIGHT": 0.6571,
    }
    overrides = realism.car_overrides({"calibration": {"mounting_yaw_error_deg": estimate}})
    cfg = load_sim_config("demo", overrides)
    assert cfg.radar.mounting_yaw_error_deg == estimate
    # every unit of the simulated vehicle, whatever the seed would have drawn (a knocked unit too)
    for seed in (0, 1, 2):
        errors = mounting_errors(cfg.radar, seed)
        assert {ch: e.yaw_deg for ch, e in errors.items()} == estimate


def test_a_run_without_an_estimate_keeps_the_drawn_mounting(realism):
    assert realism.car_overrides({"calibration": {}}) == []
    assert realism.car_overrides({}) == []
