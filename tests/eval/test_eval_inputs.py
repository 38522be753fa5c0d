"""``radarslam eval`` on damaged or incomplete results folders: one-line errors naming the file."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from typer.testing import CliRunner

from radarslam.cli import app
from radarslam.config import load_config
from radarslam.errors import ConfigError, DataError
from radarslam.eval.evaluate import EvalConfig, evaluate_results
from radarslam.geometry import se2_to_matrix
from radarslam.io.loops import LoopCandidate, NodeKey
from radarslam.io.results import read_results
from radarslam.slam.outputs import SessionResult, write_results

T0 = 1_600_000_000_000_000


def _session(name: str, start_us: int, n: int = 30) -> SessionResult:
    t = start_us + np.arange(n, dtype=np.int64) * 500_000
    gt = np.stack([se2_to_matrix(0.8 * i, 0.1 * np.sin(i / 3), 0.02 * i) for i in range(n)])
    slam = np.stack([g @ se2_to_matrix(0.05, -0.03, 0.001) for g in gt])
    odo = np.stack([g @ se2_to_matrix(0.01 * i, 0.0, 0.0) for i, g in enumerate(gt)])
    return SessionResult(name, t, slam, odo, gt)


def _write(d, names=("scene-a", "scene-b"), loops=True):
    sessions = [_session(s, T0 + k * 3_600_000_000) for k, s in enumerate(names)]
    lcs = None
    if loops:
        a = sessions[0]
        lcs = [
            LoopCandidate(
                NodeKey(a.name, 20), NodeKey(a.name, 2), int(a.timestamps_us[20]),
                int(a.timestamps_us[2]), 0.3, False, "fitness 0.1 < 0.5",
            )
        ]  # fmt: skip
    write_results(d, sessions, loops=lcs, components=[list(names)], plots=False)
    return sessions


def _cfg():
    return EvalConfig(plots=False)


def test_run_json_that_is_binary_or_has_empty_components(tmp_path):
    _write(tmp_path)
    run = tmp_path / "run.json"
    meta = json.loads(run.read_text())
    run.write_bytes(b"\xbf\xfe\x00\x81binary")
    with pytest.raises(DataError, match=r"run\.json: not a UTF-8 text file"):
        evaluate_results(tmp_path, _cfg())
    run.write_text(json.dumps({**meta, "sessions": ["../../etc/passwd"]}))
    with pytest.raises(DataError, match=r"run\.json: session name '\.\./\.\./etc/passwd' cannot"):
        evaluate_results(tmp_path, _cfg())
    run.write_text(json.dumps({**meta, "components": []}))
    with pytest.raises(DataError, match=r"run\.json: 'components' must be a non-empty list"):
        evaluate_results(tmp_path, _cfg())
    run.write_text(json.dumps({**meta, "components": [[], ["scene-a", "scene-b"]]}))
    with pytest.raises(DataError, match=r"run\.json: 'components'"):
        evaluate_results(tmp_path, _cfg())
    run.write_text(json.dumps({**meta, "components": [["scene-a"], ["scene-a", "scene-b"]]}))
    with pytest.raises(DataError, match=r"run\.json: 'components' lists scene-a more than once"):
        evaluate_results(tmp_path, _cfg())


def test_a_results_format_of_another_version_is_refused(tmp_path):
    _write(tmp_path)
    run = tmp_path / "run.json"
    meta = json.loads(run.read_text())
    run.write_text(json.dumps({**meta, "format": "radarslam-results/9"}))
    with pytest.raises(DataError) as err:
        evaluate_results(tmp_path, _cfg())
    assert str(err.value) == (
        f"{run}: results format 'radarslam-results/9' is not supported "
        "(this code reads radarslam-results/1)"
    )


@pytest.mark.parametrize(
    ("index", "message"),
    [
        (9999, "key frame scene-a#9999 at {t} us is key frame 20 of 'scene-a', not 9999"),
        (-3, "negative key-frame index"),
    ],
)
def test_a_loop_whose_index_and_time_disagree_is_refused(tmp_path, index, message):
    sessions = _write(tmp_path)
    loops = tmp_path / "loops.csv"
    lines = loops.read_text().splitlines()
    assert lines[1].startswith("scene-a,20,")
    lines[1] = lines[1].replace("scene-a,20,", f"scene-a,{index},", 1)
    loops.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError) as err:
        evaluate_results(tmp_path, _cfg())
    text = str(err.value)
    assert text.startswith(f"{loops}:2") and message.format(t=sessions[0].timestamps_us[20]) in text


@pytest.mark.parametrize(
    ("continues", "message"),
    [
        (["scene-b"], "'continues' must map session names to session names"),
        ({"scene-b": "scene-x"}, "'continues' names 'scene-b' -> 'scene-x', not both among"),
        ({"scene-a": "scene-b"}, "'continues': 'scene-a' continues 'scene-b', which is not listed"),
    ],
)
def test_run_json_continues_names_earlier_sessions(tmp_path, continues, message):
    _write(tmp_path)
    run = tmp_path / "run.json"
    meta = json.loads(run.read_text())
    assert meta["sessions"] == ["scene-a", "scene-b"]
    run.write_text(json.dumps({**meta, "continues": continues}))
    with pytest.raises(DataError, match=re.escape(f"{run}: {message}")):
        evaluate_results(tmp_path, _cfg())
    run.write_text(json.dumps({**meta, "continues": {"scene-b": "scene-a"}}))
    assert read_results(tmp_path).continues == {"scene-b": "scene-a"}
    assert evaluate_results(tmp_path, _cfg()).loops is not None


def test_missing_slam_poses_of_a_listed_session_names_the_file(tmp_path):
    _write(tmp_path)
    (tmp_path / "poses_scene-a.tum").unlink()  # odometry_ and gt_ remain
    (tmp_path / "poses_scene-a.kitti").unlink()  # else read with the TUM files' timestamps
    with pytest.raises(DataError) as err:
        evaluate_results(tmp_path, _cfg())
    assert str(err.value) == (
        f"{tmp_path / 'poses_scene-a.tum'}: missing (run.json lists session 'scene-a')"
    )


def test_folder_without_run_json_is_incomplete(tmp_path):
    _write(tmp_path)
    (tmp_path / "run.json").unlink()  # what an interrupted writer used to leave
    with pytest.raises(DataError, match=r"no run\.json: not a complete results folder"):
        evaluate_results(tmp_path, _cfg())


def test_only_sessions_listed_in_run_json_are_evaluated(tmp_path):
    _write(tmp_path)
    run = tmp_path / "run.json"  # scene-b's files are left over from an older run
    run.write_text(json.dumps({"format": "radarslam-results/1", "sessions": ["scene-a"]}))
    for stem in ("poses", "odometry", "gt"):
        (tmp_path / f"{stem}_scene-b.tum").write_text("garbage that must not be read\n")
    report = evaluate_results(tmp_path, _cfg())
    assert report.sessions == ["scene-a"] and set(report.per_session) == {"scene-a"}


def test_empty_ground_truth_is_blamed(tmp_path):
    _write(tmp_path)
    (tmp_path / "gt_scene-a.tum").write_text("# timestamp_s tx ty tz qx qy qz qw\n")
    with pytest.raises(DataError) as err:
        evaluate_results(tmp_path, _cfg())
    assert str(err.value).startswith(f"{tmp_path / 'gt_scene-a.tum'}: 0 ground-truth poses")


def test_bad_loops_rows_name_the_file_and_line(tmp_path):
    _write(tmp_path)
    loops = tmp_path / "loops.csv"
    lines = loops.read_text().splitlines()
    lines[1] = lines[1].replace("scene-a", "scene-0777", 1)
    loops.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError) as err:
        evaluate_results(tmp_path, _cfg())
    assert (
        str(err.value) == f"{loops}:2: no ground truth for session 'scene-0777' (not in this run)"
    )
    loops.write_bytes(b"\xfc\x00\x81" * 50)
    with pytest.raises(DataError, match=r"loops\.csv: not a UTF-8 text file"):
        evaluate_results(tmp_path, _cfg())


def test_drift_segment_lengths_are_checked_by_the_config():
    with pytest.raises(ConfigError) as err:
        load_config(EvalConfig, None, ["drift_segment_lengths_m=[]"])
    assert "'drift_segment_lengths_m'" in str(err.value) and "at least one" in str(err.value)
    with pytest.raises(ConfigError, match=r"drift_segment_lengths_m.*finite and > 0"):
        load_config(EvalConfig, None, ["drift_segment_lengths_m=[100, -5]"])


@pytest.mark.parametrize("case", ["plots_is_a_file", "metrics_is_a_folder"])
def test_unwritable_outputs_are_one_line_errors(tmp_path, case):
    _write(tmp_path)
    if case == "plots_is_a_file":
        (tmp_path / "plots").write_text("")
        match = r"plots/trajectories\.png: cannot write \(.*plots is a file, not a folder\)"
    else:
        (tmp_path / "metrics.json").mkdir()
        match = r"metrics\.json: cannot write \(Is a directory\)"
    res = CliRunner().invoke(app, ["eval", str(tmp_path)])
    assert isinstance(res.exception, DataError), res.output
    assert re.search(match, str(res.exception)), str(res.exception)
    assert not [p for p in tmp_path.rglob(".*tmp*")]


def test_a_missing_odometry_file_is_said_once(tmp_path, caplog):
    import logging

    _write(tmp_path, names=("scene-a", "scene-b", "scene-c"), loops=False)
    for name in ("scene-b", "scene-c"):
        (tmp_path / f"odometry_{name}.tum").unlink()
        (tmp_path / f"odometry_{name}.kitti").unlink()
    with caplog.at_level(logging.WARNING, logger="radarslam.eval"):
        report = evaluate_results(tmp_path, _cfg())
    assert [r.getMessage() for r in caplog.records] == [
        f"{tmp_path / 'odometry_scene-b.tum'}: missing; session 'scene-b' is evaluated without "
        "its odometry (2 of 3 session(s) without)"
    ]
    assert "odometry" in report.per_session["scene-a"]
    assert "odometry" not in report.per_session["scene-b"]


def test_kitti_files_are_read_where_the_tum_twin_is_missing(tmp_path):
    _write(tmp_path, loops=False)
    before = evaluate_results(tmp_path, _cfg(), write=False)
    for stem in ("poses", "odometry"):
        (tmp_path / f"{stem}_scene-a.tum").unlink()
    after = evaluate_results(tmp_path, _cfg(), write=False)
    for kind in ("slam", "odometry"):
        a = before.per_session["scene-a"][kind].as_dict()
        b = after.per_session["scene-a"][kind].as_dict()
        assert a == pytest.approx(b, abs=1e-9)
    # a KITTI file with a pose more than the others cannot borrow their timestamps
    kitti = tmp_path / "poses_scene-a.kitti"
    kitti.write_text(kitti.read_text() + kitti.read_text().splitlines()[-1] + "\n")
    with pytest.raises(DataError, match=r"poses_scene-a\.kitti: KITTI poses carry no timestamps"):
        evaluate_results(tmp_path, _cfg(), write=False)


def _write_odometry(d, names=("scene-a", "scene-b"), method="ours"):
    """An odometry folder as ``radarslam odometry`` writes it (frames: the sessions' poses)."""
    from radarslam.io.results import write_results_folder, write_trajectories

    sessions = [_session(s, T0 + k * 3_600_000_000) for k, s in enumerate(names)]

    def contents(out):
        for s in sessions:
            traj = {"odometry": s.odometry_poses, "gt": s.gt_poses}
            write_trajectories(out, s.name, s.timestamps_us, traj)

    write_results_folder(d, names, "odometry", contents, method=method)
    return sessions


def test_an_odometry_folder_has_odometry_rows_only(tmp_path):
    _write_odometry(tmp_path)
    report = evaluate_results(tmp_path, _cfg())
    assert (report.kind, report.method) == ("odometry", "ours")
    assert all(set(kinds) == {"odometry"} for kinds in report.per_session.values())
    assert set(report.run) == {"odometry"} and report.loops is None
    # the same trajectories in a SLAM folder give the same odometry numbers
    _write(tmp_path / "slam", loops=False)
    slam = evaluate_results(tmp_path / "slam", _cfg())
    assert slam.kind == "slam" and set(slam.per_session["scene-a"]) == {"odometry", "slam"}
    for s in ("scene-a", "scene-b"):
        a = report.per_session[s]["odometry"].as_dict()
        assert a == pytest.approx(slam.per_session[s]["odometry"].as_dict(), abs=1e-9)
    res = CliRunner().invoke(app, ["eval", str(tmp_path), "--no-plots"])
    assert res.exit_code == 0, res.output
    assert "slam" not in res.output and "loops:" not in res.output


def test_an_odometry_folder_needs_its_odometry_and_a_known_kind(tmp_path):
    _write_odometry(tmp_path)
    (tmp_path / "loops.csv").write_text("not read in an odometry folder\n")
    evaluate_results(tmp_path, _cfg(), write=False)
    for ext in ("tum", "kitti"):
        (tmp_path / f"odometry_scene-b.{ext}").unlink()
    with pytest.raises(DataError) as err:
        evaluate_results(tmp_path, _cfg(), write=False)
    assert str(err.value) == (
        f"{tmp_path / 'odometry_scene-b.tum'}: missing (run.json lists session 'scene-b')"
    )
    run = tmp_path / "run.json"
    meta = json.loads(run.read_text())
    for bad, match in (({"kind": "lidar"}, "'kind' must be one of slam, odometry, got 'lidar'"),
                       ({"method": 3}, "'method' must be a string, got 3")):  # fmt: skip
        run.write_text(json.dumps({**meta, **bad}))
        with pytest.raises(DataError, match=re.escape(f"{run}: {match}")):
            evaluate_results(tmp_path, _cfg(), write=False)
