"""The benchmark scripts answer a bad argument with one line and exit status 2, like the CLI."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


@pytest.mark.parametrize(
    ("script", "args", "names"),
    [
        ("odometry.py", ["--set", "fusion.gate_chi2=-1"], "fusion.gate_chi2"),
        ("odometry.py", ["--set", "foo.bar=1"], "foo"),
        # before generating the (missing) city: nothing is written
        (
            "slam.py",
            ["--set", "loops.no_such_key=1", "--dataroot", "{tmp}/city", "--out", "{tmp}/out"],
            "no_such_key",
        ),
        ("slam_settings.py", ["--set", "loops.no_such_key=1", "--out", "{tmp}/out"], "no_such_key"),
        ("slam_settings.py", ["--runs", "long,s8", "--out", "{tmp}/out"], "--runs"),
        ("odometry.py", ["--dataroot", "{tmp}/none"], "no such folder"),
        ("odometry.py", ["--doppler-seeds", "0"], "--doppler-seeds"),
        ("realism.py", ["--set", "world.x=1", "--work", "{tmp}/work"], "world"),
        ("degraded.py", ["--dataroot", "{tmp}/none", "--work", "{tmp}/work"], "no such folder"),
        ("degraded.py", ["--scenes", "scene-9999", "--work", "{tmp}/work"], "scene-9999"),
        (
            "degraded.py",
            ["--set", "fusion.calibration.pass_frame_stride=0", "--work", "{tmp}/work"],
            "pass_frame_stride",
        ),
    ],
)
def test_bad_argument_is_one_line_and_status_2(tmp_path, script, args, names):
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    out = subprocess.run(
        [sys.executable, str(BENCH / script), *args], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 2, out.stderr
    lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and names in lines[0], out.stderr
    assert not list(tmp_path.iterdir())  # nothing written


def test_a_bench_city_from_another_simulator_config_is_named(tmp_path):
    # The SLAM bench reuses its city: one generated before a simulator default changed is
    # reported with the keys that differ, not measured as if it were today's world.
    import importlib.util

    import yaml

    from radarslam.config import dump_config
    from radarslam.sim.config import load_sim_config

    spec = importlib.util.spec_from_file_location("bench_slam", BENCH / "slam.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    overrides = ["schedule.n_logs=4", "schedule.n_routes=1"]
    (tmp_path / "synthetic").mkdir()
    stored = yaml.safe_load(dump_config(load_sim_config("city", overrides)))
    stored["jobs"] = 7  # not part of the world
    (tmp_path / "synthetic" / "config.yaml").write_text(yaml.safe_dump(stored))
    assert bench.stale_keys(tmp_path, overrides) == []
    stored["radar"]["noise"]["doppler_scale_error"] = 0.0
    (tmp_path / "synthetic" / "config.yaml").write_text(yaml.safe_dump(stored))
    now = load_sim_config("city", overrides).radar.noise.doppler_scale_error
    assert bench.stale_keys(tmp_path, overrides) == [
        f"radar.noise.doppler_scale_error: 0.0 there, {now!r} now"
    ]
    # The demo preset's world is judged against the demo preset, not the city's.
    stored = yaml.safe_load(dump_config(load_sim_config("demo", [])))
    (tmp_path / "synthetic" / "config.yaml").write_text(yaml.safe_dump(stored))
    assert bench.stale_keys(tmp_path, [], preset="demo") == []
    assert "city.n_blocks_x" in " ".join(bench.stale_keys(tmp_path, []))


def test_the_slam_bench_takes_the_measurement_time_truth_from_synthetic_dataroots_only(
    tmp_path, tiny_dataroot
):
    import importlib.util

    spec = importlib.util.spec_from_file_location("bench_slam", BENCH / "slam.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    (tmp_path / "v1.0-mini").mkdir()  # a nuScenes layout without the simulator's truth
    assert bench.measurement_time_truth(tmp_path, "v1.0-mini") is None
    truth = bench.measurement_time_truth(tiny_dataroot, "v1.0-mini")
    assert truth is not None and truth.clock_offset_s("scene-0001") == 0.0  # tiny: pose clock


def test_the_settings_bench_reruns_a_row_when_the_weights_change(tmp_path):
    # Rows are cached by config digest; `loops.checkpoint: null` resolves to whatever weights
    # are shipped, so the digest must follow the file, not the setting.
    import importlib.util
    import shutil

    from radarslam.config import load_config
    from radarslam.place_recognition.recognizer import DEFAULT_CHECKPOINT
    from radarslam.slam.config import SlamConfig

    spec = importlib.util.spec_from_file_location("bench_slam_settings", BENCH / "slam_settings.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    copy = tmp_path / "weights.pt"
    shutil.copyfile(DEFAULT_CHECKPOINT, copy)
    cfg = load_config(SlamConfig, None, [f"loops.checkpoint={copy}"])
    same = bench.config_digest(cfg)
    assert bench.config_digest(cfg) == same
    with copy.open("ab") as f:
        f.write(b"\0")
    assert bench.config_digest(cfg) != same
    off = load_config(SlamConfig, None, ["loops.enabled=false", "loops.checkpoint=/no/such.pt"])
    assert bench.config_digest(off)  # no weights read when loop closure is off


def test_the_slam_bench_reads_a_small_map_as_a_scale_above_one():
    import importlib.util

    from radarslam.geometry import se2_to_matrix

    spec = importlib.util.spec_from_file_location("bench_slam", BENCH / "slam.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    gt = np.stack([se2_to_matrix(3.0 * k, 0.05 * k**2, 0.1 * k) for k in range(40)])
    small = gt.copy()
    small[:, :2, 3] *= 0.999  # a map 0.1 % small
    fit = bench.map_scale(small, gt)
    assert fit["scale_slam_in_map_true_time"] == pytest.approx(1 / 0.999, rel=1e-9)
    assert fit["ate_slam_in_map_true_time_sim2_m"] == pytest.approx(0.0, abs=1e-9)
    assert np.isnan(bench.map_scale(gt[:1], gt[:1])["scale_slam_in_map_true_time"])


def test_the_slam_bench_splits_loop_errors_by_how_the_passes_face():
    import importlib.util
    from types import SimpleNamespace

    from radarslam.geometry import se2_to_matrix
    from radarslam.io.loops import NodeKey

    spec = importlib.util.spec_from_file_location("bench_slam", BENCH / "slam.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    truth = {
        ("a", 0): se2_to_matrix(10.0, 5.0, 0.3),
        ("b", 0): se2_to_matrix(11.0, 5.5, 0.35),  # the same way
        ("c", 0): se2_to_matrix(9.0, 4.0, 0.3 + np.pi),  # the other way
    }

    def loop(q, c, error):
        c_from_q = np.linalg.inv(truth[(c, 0)]) @ truth[(q, 0)]
        return SimpleNamespace(
            query=NodeKey(q, 0),
            candidate=NodeKey(c, 0),
            query_timestamp_us=0,
            candidate_timestamp_us=0,
            candidate_from_query=c_from_q @ se2_to_matrix(*error),
        )

    loops = [loop("a", "b", (0.1, 0.0, 0.0)), loop("b", "a", (0.3, 0.0, 0.01)),
             loop("a", "c", (0.0, -0.25, 0.0)), loop("c", "b", (0.02, -0.15, 0.0))]  # fmt: skip
    out = bench.loop_bias(loops, lambda s, t: truth[(s, t)])
    assert out["loops_same_n"] == 2 and out["loops_opposite_n"] == 2
    assert out["loops_same_along_m"] == pytest.approx(0.2, abs=1e-9)
    assert out["loops_same_across_m"] == pytest.approx(0.0, abs=1e-9)
    assert out["loops_opposite_along_m"] == pytest.approx(0.01, abs=1e-9)
    assert out["loops_opposite_across_m"] == pytest.approx(-0.2, abs=1e-9)
    empty = bench.loop_bias(loops[:1], lambda s, t: truth[(s, t)])
    assert empty["loops_opposite_n"] == 0 and np.isnan(empty["loops_opposite_across_m"])
