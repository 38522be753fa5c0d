"""bench/odometry.py: the ATE split and the clock offsets it pools over segments."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


@pytest.fixture
def odobench(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCH))
    spec = importlib.util.spec_from_file_location("bench_odometry", BENCH / "odometry.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _segment(odobench, lead_s: float, seconds: float = 12.0) -> dict:
    """A braking drive whose estimate runs ``lead_s`` ahead of its stamps, as a bench result."""
    t_us = 1_700_000_000_000_000 + np.arange(0, int(seconds * 1e6), 75_000, dtype=np.int64)

    def poses(t_s):
        x = np.where(t_s < 8.0, 8.0 * t_s - 0.5 * t_s**2, 32.0)
        out = np.tile(np.eye(4), (len(t_s), 1, 1))
        out[:, 0, 3] = x
        return out

    t_s = (t_us - t_us[0]) * 1e-6
    est = poses(t_s + lead_s)
    return {"t": t_us, "gt": poses(t_s), "ours": est, "ours_cpu_ms": 1.0}


def test_segment_metrics_split_the_ate_and_find_the_clock_offset(odobench):
    row = odobench.segment_metrics(_segment(odobench, 0.04), "ours")
    assert row["clock_offset_ms"] == pytest.approx(40.0)
    assert row["ate_clock_m"] < 0.01 * row["ate_m"]
    assert row["ate_cross_m"] == pytest.approx(0.0, abs=1e-9)  # a straight drive
    assert row["ate_along_m"] == pytest.approx(row["ate_m"])


def test_one_clock_offset_pooled_over_segments(odobench):
    # two segments 20 and 60 ms ahead: the one offset that fits both lies between
    rows = [odobench.segment_metrics(_segment(odobench, lead), "ours") for lead in (0.02, 0.06)]
    pooled = odobench.common_clock(rows)
    assert 20.0 < pooled["clock_offset_common_ms"] < 60.0
    per_segment = np.sqrt(np.mean([r["ate_clock_m"] ** 2 for r in rows]))
    assert pooled["ate_clock_common_m"] > per_segment + 0.01
    none = odobench.common_clock([{**rows[0], "clock_count": 0}])
    assert np.isnan(none["clock_offset_common_ms"]) and np.isnan(none["ate_clock_common_m"])


def test_segment_metrics_read_a_short_estimate_as_a_scale_above_one(odobench):
    seg = _segment(odobench, 0.0)
    seg["ours"] = seg["ours"].copy()
    seg["ours"][:, :3, 3] *= 0.997  # the estimate 0.3 % short
    row = odobench.segment_metrics(seg, "ours")
    assert row["sim2_scale"] == pytest.approx(1 / 0.997, rel=1e-9)
    assert row["ate_along_m"] > 0.01  # without the scale the shortfall shows along the track
    pooled = odobench.pooled([row, odobench.segment_metrics(_segment(odobench, 0.0), "ours")])
    assert 1.0 < pooled["sim2_scale"] < 1 / 0.997


def test_a_scene_that_stands_leaves_the_pooled_scale_alone(odobench):
    seg = _segment(odobench, 0.0)
    seg["ours"] = seg["ours"].copy()
    seg["ours"][:, :3, 3] *= 0.997
    moving = odobench.segment_metrics(seg, "ours")
    t_us = seg["t"]
    rng = np.random.default_rng(5)
    gt = np.tile(np.eye(4), (len(t_us), 1, 1))
    gt[:, 0, 3] = np.linspace(0.0, 0.03, len(t_us))  # creeping 3 cm at a light
    est = gt.copy()
    est[:, :2, 3] += rng.normal(scale=0.002, size=(len(t_us), 2))
    standing = odobench.segment_metrics(
        {"t": t_us, "gt": gt, "ours": est, "ours_cpu_ms": 1.0}, "ours"
    )
    assert np.isnan(standing["sim2_scale"])
    pooled = odobench.pooled([moving, standing])
    assert pooled["sim2_scale"] == pytest.approx(1 / 0.997, rel=1e-9)
