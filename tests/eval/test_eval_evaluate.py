import json

import numpy as np
import pytest
from typer.testing import CliRunner

from radarslam.cli import app
from radarslam.errors import DataError
from radarslam.eval.evaluate import EvalConfig, associate, evaluate_results
from radarslam.eval.metrics import ate
from radarslam.geometry import se2_to_matrix
from radarslam.io.loops import LoopCandidate, NodeKey
from radarslam.slam.outputs import SessionResult, write_results
from radarslam.slam.synthetic_graph import multilap_circuit


def _results(tmp_path, with_loops=True):
    sg = multilap_circuit(num_laps=2, poses_per_lap=60, seed=4)
    n = len(sg.gt)
    ts = 1_600_000_000_000_000 + np.arange(n, dtype=np.int64) * 500_000
    rng = np.random.default_rng(0)
    slam = np.stack([g @ se2_to_matrix(*rng.normal(scale=[0.2, 0.2, 0.005])) for g in sg.gt])
    # a second session: the first lap again, an hour later, shifted in its own frame
    shift = se2_to_matrix(3.0, -2.0, 0.1)
    b_gt = sg.gt[:60]
    b_odo = np.stack([shift @ p for p in sg.dead_reckoning[:60]])
    sessions = [
        SessionResult("scene-a", ts, slam, sg.dead_reckoning, sg.gt),
        SessionResult("scene-b", ts[:60] + 3_600_000_000, b_gt.copy(), b_odo, b_gt),
    ]
    loops = None
    if with_loops:
        loops = [
            LoopCandidate(
                NodeKey("scene-a", lp.j),
                NodeKey("scene-a", lp.i),
                int(ts[lp.j]),
                int(ts[lp.i]),
                0.2,
                True,
                "ok",
                lp.i_from_j,
            )
            for lp in sg.loops
        ]
        # a wrong accepted loop and a rejected one
        loops.append(
            LoopCandidate(
                NodeKey("scene-a", 100),
                NodeKey("scene-a", 10),
                int(ts[100]),
                int(ts[10]),
                0.4,
                True,
                "ok",
                se2_to_matrix(0.0, 0.0, 0.0),
            )
        )
        loops.append(
            LoopCandidate(
                NodeKey("scene-b", 5),
                NodeKey("scene-a", 5),
                int(ts[5] + 3_600_000_000),
                int(ts[5]),
                0.5,
                False,
                "fitness 0.1 < 0.5",
            )
        )
    write_results(tmp_path, sessions, loops=loops)
    return sg, ts, slam


def test_evaluate_results_folder(tmp_path):
    sg, _ts, slam = _results(tmp_path)
    report = evaluate_results(tmp_path, EvalConfig(plots=True))
    assert report.sessions == ["scene-a", "scene-b"]
    a = report.per_session["scene-a"]
    assert a["slam"].ate_rmse_m == pytest.approx(ate(slam, sg.gt).rmse_m, abs=1e-9)
    assert a["odometry"].ate_rmse_m == pytest.approx(ate(sg.dead_reckoning, sg.gt).rmse_m)
    assert a["odometry"].ate_first_rmse_m > a["odometry"].ate_rmse_m
    b = report.per_session["scene-b"]
    assert b["slam"].ate_rmse_m == pytest.approx(0.0, abs=1e-9)
    assert b["odometry"].ate_rmse_m > 0.1  # alignment cannot remove drift
    # the run-level joint alignment of odometry suffers from b's own frame, SLAM does not
    run = report.run
    assert run["odometry"]["ate_joint_rmse_m"] > run["odometry"]["ate_rmse_m"]
    assert run["slam"]["num_poses"] == 180
    lm = report.loops
    n_true = len(sg.loops)
    assert lm.num_candidates == n_true + 2 and lm.num_accepted == n_true + 1
    assert lm.precision == pytest.approx(n_true / (n_true + 1))
    data = json.loads((tmp_path / "metrics.json").read_text())
    assert data["per_session"]["scene-a"]["slam"]["ate_rmse_m"] == pytest.approx(
        a["slam"].ate_rmse_m
    )
    assert data["loops"]["num_correct"] == n_true
    for name in ("trajectories.png", "errors_scene-a.png", "errors_scene-b.png"):
        assert (tmp_path / "plots" / name).stat().st_size > 10_000
    assert (tmp_path / "poses_scene-a.kitti").is_file()
    assert json.loads((tmp_path / "run.json").read_text())["sessions"] == ["scene-a", "scene-b"]


def test_eval_cli(tmp_path):
    _results(tmp_path, with_loops=False)
    res = CliRunner().invoke(app, ["eval", str(tmp_path), "--no-plots",
                                   "--set", "rpe_distance_m=5"])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "scene-a" in res.output and "RPE 5m" in res.output
    assert "scale of a similarity alignment" in res.output
    data = json.loads((tmp_path / "metrics.json").read_text())
    assert data["per_session"]["scene-a"]["odometry"]["sim2_scale"] > 0
    assert data["loops"] is None and data["config"]["rpe_distance_m"] == 5.0
    assert not (tmp_path / "plots").exists()


def test_eval_errors(tmp_path):
    with pytest.raises(DataError, match="does not exist"):
        evaluate_results(tmp_path / "nope")
    (tmp_path / "file").write_text("")
    with pytest.raises(DataError, match="is a file, not a results folder"):
        evaluate_results(tmp_path / "file")
    (tmp_path / "file").unlink()
    with pytest.raises(DataError, match="no poses_"):
        evaluate_results(tmp_path)
    _results(tmp_path, with_loops=False)
    (tmp_path / "gt_scene-b.tum").unlink()
    (tmp_path / "gt_scene-b.kitti").unlink()  # else read with the other files' timestamps
    with pytest.raises(DataError, match=r"gt_scene-b\.tum: missing \(run\.json lists session"):
        evaluate_results(tmp_path)
    with pytest.raises(DataError, match="cannot be used in file names"):
        write_results(
            tmp_path, [SessionResult("a/b", np.zeros(1, dtype=np.int64), np.eye(4)[None])]
        )


def test_odometry_joint_ate_starts_every_session_on_its_ground_truth(tmp_path):
    # Odometry sessions start in frames of their own (b here 500 m off and turned); placed on
    # their first ground-truth pose they are joined by one alignment, and what is left is drift.
    t = np.arange(20, dtype=np.int64) * 500_000 + 1_000_000
    gt_a = np.stack([se2_to_matrix(0.5 * i, 0.0, 0.0) for i in range(20)])
    gt_b = np.stack([se2_to_matrix(0.0, 0.5 * i, np.pi / 2) for i in range(20)])
    off = se2_to_matrix(500.0, -300.0, 1.0)
    drifted = np.stack([g @ se2_to_matrix(0.01 * i, 0.0, 0.0) for i, g in enumerate(gt_b)])
    sessions = [
        SessionResult("a", t, gt_a.copy(), gt_a.copy(), gt_a),
        SessionResult("b", t + 20_000_000, gt_b.copy(), off @ drifted, gt_b),
    ]
    write_results(tmp_path, sessions, plots=False)
    run = evaluate_results(tmp_path, EvalConfig(plots=False)).run["odometry"]
    assert run["joint_sessions"] == 2
    placed = np.concatenate([gt_a, drifted])  # b started on gt_b[0]: drifted as written
    assert run["ate_joint_rmse_m"] == pytest.approx(
        ate(placed, np.concatenate([gt_a, gt_b]), align="se2").rmse_m
    )
    assert 0.01 < run["ate_joint_rmse_m"] < 0.2


def test_associate_nearest_within_tolerance():
    gt = np.array([0, 100, 200, 300])
    i_e, i_g = associate(np.array([101, 260, 500, 0]), gt, 50)
    assert list(i_e) == [0, 1, 3] and list(i_g) == [1, 3, 0]


def test_every_component_of_several_sessions_gets_its_own_joint_ate(tmp_path):
    # "b" and "c" were linked to each other but not to the map: together they live in one frame
    # of their own (500 m away and turned), so aligned on their own they agree; "c" is also
    # 0.3 m off across its track there, which that joint ATE must show.
    t = np.arange(20, dtype=np.int64) * 500_000 + 1_000_000
    gt_a = np.stack([se2_to_matrix(0.5 * i, 0.0, 0.0) for i in range(20)])
    gt_b = np.stack([se2_to_matrix(0.0, 0.5 * i, np.pi / 2) for i in range(20)])
    gt_c = np.stack([se2_to_matrix(5.0, 0.5 * i, np.pi / 2) for i in range(20)])
    off = se2_to_matrix(500.0, -300.0, 1.0)
    shifted = np.stack([g @ se2_to_matrix(0.0, 0.3, 0.0) for g in gt_c])
    sessions = [
        SessionResult("a", t, gt_a.copy(), gt_a.copy(), gt_a),
        SessionResult("b", t + 20_000_000, off @ gt_b, gt_b.copy(), gt_b),  # slam, odometry
        SessionResult("c", t + 40_000_000, off @ shifted, gt_c.copy(), gt_c),
    ]
    write_results(tmp_path, sessions, components=[["a"], ["b", "c"]], plots=False)
    run = evaluate_results(tmp_path, EvalConfig(plots=False)).run
    (comp,) = run["slam"]["components_joint"]  # "a" alone has none of its own
    assert comp["component"] == 1 and comp["sessions"] == ["b", "c"]
    expected = ate(np.concatenate([gt_b, shifted]), np.concatenate([gt_b, gt_c]), align="se2")
    assert comp["ate_joint_rmse_m"] == pytest.approx(expected.rmse_m)
    assert 0.1 < comp["ate_joint_rmse_m"] < 0.3
    # the odometry over the same sessions, each started on its ground truth: no error here
    (odo,) = run["odometry"]["components_joint"]
    assert odo["sessions"] == ["b", "c"] and odo["ate_joint_rmse_m"] < 1e-6
    assert run["slam"]["joint_sessions"] == 1
    # one such component: no table; with the map of two sessions as well, a row for each
    out = CliRunner().invoke(app, ["eval", str(tmp_path), "--no-plots"]).output
    assert "each aligned on its own" not in out
    write_results(tmp_path, [*sessions, SessionResult("d", t + 60_000_000, gt_a, gt_a, gt_a)],
                  components=[["b", "c"], ["a", "d"]], plots=False)  # fmt: skip
    out = CliRunner().invoke(app, ["eval", str(tmp_path), "--no-plots"]).output
    assert "each aligned on its own" in out
    rows = [line.split() for line in out.splitlines() if line.startswith("│")]
    assert ["│", "0", "│", "2", "│"] == rows[-2][:5] and ["│", "1", "│", "2", "│"] == rows[-1][:5]


def test_slam_joint_ate_covers_the_anchored_map_only(tmp_path):
    # Session "b" never joined the map: its SLAM poses live in their own frame (here 500 m away
    # and rotated). The joint SLAM ATE must cover the anchored component only.
    t = np.arange(20, dtype=np.int64) * 500_000 + 1_000_000
    gt_a = np.stack([se2_to_matrix(0.5 * i, 0.0, 0.0) for i in range(20)])
    gt_b = np.stack([se2_to_matrix(0.0, 0.5 * i, np.pi / 2) for i in range(20)])
    off = se2_to_matrix(500.0, -300.0, 1.0)
    sessions = [
        SessionResult("a", t, gt_a.copy(), gt_a.copy(), gt_a),
        SessionResult("b", t + 20_000_000, off @ gt_b, off @ gt_b, gt_b),
    ]
    write_results(tmp_path, sessions, components=[["a"], ["b"]], plots=False)
    report = evaluate_results(tmp_path, EvalConfig(plots=True))
    assert report.run["slam"]["joint_sessions"] == 1
    assert report.run["slam"]["ate_joint_rmse_m"] < 1e-6
    # the odometry's joint ATE covers the same sessions, each started on its ground truth
    assert report.run["odometry"]["joint_sessions"] == 1
    assert report.run["odometry"]["ate_joint_rmse_m"] < 1e-6
    assert (tmp_path / "plots" / "trajectories.png").is_file()
    with pytest.raises(DataError, match="components"):
        (tmp_path / "run.json").write_text(
            json.dumps({"sessions": ["a", "b"], "components": [["c"]]})
        )
        evaluate_results(tmp_path, EvalConfig(plots=False))


def test_eval_reports_the_ate_split_and_the_clock_offset_of_the_ground_truth(tmp_path):
    ts = 1_600_000_000_000_000 + np.arange(0, 10_000_000, 50_000, dtype=np.int64)

    def drive(t_s):  # accelerating through a gentle left turn
        x = 2.0 * t_s + 0.4 * t_s**2
        return np.stack([se2_to_matrix(x, 0.01 * x**2, 0.02 * x) for x in x])

    t_s = (ts - ts[0]) * 1e-6
    gt = drive(t_s)
    odometry = drive(t_s + 0.04)  # every pose 40 ms ahead of its stamp
    write_results(tmp_path, [SessionResult("scene-a", ts, gt.copy(), odometry, gt)])
    report = evaluate_results(tmp_path, EvalConfig(plots=False))
    m = report.per_session["scene-a"]["odometry"]
    a = ate(odometry, gt)
    assert m.ate_along_m == pytest.approx(a.along_rmse_m)
    assert m.ate_cross_m == pytest.approx(a.cross_rmse_m)
    assert m.ate_along_m > 2 * m.ate_cross_m  # a clock offset shows mostly along the track
    assert m.clock_offset_ms == pytest.approx(40.0)
    assert m.ate_at_clock_offset_m < 0.05 * m.ate_rmse_m
    exact = report.per_session["scene-a"]["slam"]
    assert exact.clock_offset_ms == 0.0
    assert exact.ate_at_clock_offset_m == pytest.approx(0.0, abs=1e-9)
    data = json.loads((tmp_path / "metrics.json").read_text())["per_session"]["scene-a"]
    assert data["odometry"]["clock_offset_ms"] == pytest.approx(40.0)
    off = evaluate_results(tmp_path, EvalConfig(plots=False, clock_offset_max_ms=0), write=False)
    assert off.per_session["scene-a"]["odometry"].as_dict()["clock_offset_ms"] is None


def test_eval_reports_the_scale_of_a_short_estimate(tmp_path):
    ts = 1_600_000_000_000_000 + np.arange(0, 10_000_000, 50_000, dtype=np.int64)
    gt = np.stack([se2_to_matrix(5.0 * t, 0.02 * (5.0 * t) ** 2, 0.0) for t in (ts - ts[0]) * 1e-6])
    short = gt.copy()
    short[:, :2, 3] *= 0.998  # a Doppler speed read 0.2 % slow
    write_results(tmp_path, [SessionResult("scene-a", ts, gt.copy(), short, gt)])
    evaluate_results(tmp_path, EvalConfig(plots=False))
    data = json.loads((tmp_path / "metrics.json").read_text())["per_session"]["scene-a"]
    assert data["odometry"]["sim2_scale"] == pytest.approx(1 / 0.998, rel=1e-9)
    assert data["odometry"]["ate_sim2_m"] == pytest.approx(0.0, abs=1e-9)
    assert data["odometry"]["ate_rmse_m"] > 0.01
    assert data["slam"]["sim2_scale"] == pytest.approx(1.0, abs=1e-12)


def test_eval_gives_no_scale_for_a_drive_that_stands(tmp_path):
    ts = 1_600_000_000_000_000 + np.arange(0, 10_000_000, 50_000, dtype=np.int64)
    rng = np.random.default_rng(3)
    # waiting at a light: the truth creeps 3 cm, the estimate jitters by a few millimetres
    gt = np.stack([se2_to_matrix(0.003 * t, 0.0, 0.0) for t in (ts - ts[0]) * 1e-6])
    jitter = np.stack([g @ se2_to_matrix(*rng.normal(scale=[0.003, 0.003, 1e-4])) for g in gt])
    write_results(tmp_path, [SessionResult("scene-a", ts, gt.copy(), jitter, gt)])
    report = evaluate_results(tmp_path, EvalConfig(plots=False))
    odo = report.per_session["scene-a"]["odometry"]
    assert np.isnan(odo.sim2_scale)
    assert np.isfinite(odo.ate_sim2_m) and odo.ate_sim2_m < 0.01
    data = json.loads((tmp_path / "metrics.json").read_text())["per_session"]["scene-a"]
    assert data["odometry"]["sim2_scale"] is None
    # with the minimum lowered below the creep, the ratio of noise to noise comes out
    loose = evaluate_results(tmp_path, EvalConfig(plots=False, scale_min_path_m=0.0), write=False)
    assert np.isfinite(loose.per_session["scene-a"]["odometry"].sim2_scale)


def test_eval_reports_how_far_the_estimate_turns(tmp_path):
    ts = 1_600_000_000_000_000 + np.arange(0, 20_000_000, 50_000, dtype=np.int64)
    t = (ts - ts[0]) * 1e-6
    yaw = np.where(t < 5, 0.0, np.minimum(t - 5, 10) * np.pi / 20)  # 90 deg over 10 s
    xy = np.cumsum(5.0 * 0.05 * np.column_stack([np.cos(yaw), np.sin(yaw)]), axis=0)
    gt = np.stack([se2_to_matrix(x, y, h) for (x, y), h in zip(xy, yaw, strict=True)])
    far = np.stack([se2_to_matrix(x, y, 1.02 * h) for (x, y), h in zip(xy, yaw, strict=True)])
    write_results(tmp_path, [SessionResult("scene-a", ts, gt.copy(), far, gt)])
    report = evaluate_results(tmp_path, EvalConfig(plots=False))
    odo = report.per_session["scene-a"]["odometry"]
    assert odo.turn_scale == pytest.approx(1.02, abs=1e-9)
    assert odo.turned_deg == pytest.approx(90.0, abs=1e-6)
    assert report.per_session["scene-a"]["slam"].turn_scale == pytest.approx(1.0, abs=1e-12)
    data = json.loads((tmp_path / "metrics.json").read_text())
    assert data["run"]["odometry"]["turn_scale"] == pytest.approx(1.02, abs=1e-9)
    strict = evaluate_results(tmp_path, EvalConfig(plots=False, turn_scale_min_deg=91), write=False)
    assert strict.as_dict()["per_session"]["scene-a"]["odometry"]["turn_scale"] is None
