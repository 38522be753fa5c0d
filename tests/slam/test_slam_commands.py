"""``radarslam run`` / ``radarslam demo`` plumbing through the real CLI."""

from __future__ import annotations

import json

from typer.testing import CliRunner

from radarslam.cli import app


def test_run_odometry_only_writes_and_evaluates_a_results_folder(tiny_dataroot, tmp_path):
    out = tmp_path / "res"
    result = CliRunner().invoke(
        app,
        ["run", "--dataroot", str(tiny_dataroot), "--version", "v1.0-mini", "--out", str(out),
         "--no-loops", "--no-progress"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    run = json.loads((out / "run.json").read_text())
    assert len(run["sessions"]) == 2
    for name in run["sessions"]:
        for stem in ("poses", "odometry", "gt"):
            assert (out / f"{stem}_{name}.tum").is_file()
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["per_session"][run["sessions"][0]]["slam"]["ate_rmse_m"] < 0.5
    timing = json.loads((out / "timing.json").read_text())
    assert timing["key_frames"] > 30 and timing["loops"]["candidates"] == 0
    assert (out / "map.ply").is_file() and (out / "config.yaml").is_file()
    # the odometry's mounting-yaw estimate over the run, as in an odometry folder's summary
    cal = json.loads((out / "summary.json").read_text())["doppler_calibration"]
    assert set(cal["mounting_yaw_error_deg"]) == set(cal["mounting_yaw_sigma_deg"])
    assert len(cal["mounting_yaw_error_deg"]) == 5
    assert all(0 < s < 1.0 for s in cal["mounting_yaw_sigma_deg"].values())
    assert "mounting yaw error (deg) FRONT " in result.output


def test_run_over_a_drive_cut_into_scenes_reports_one_drive(sim_dataroot, tmp_path):
    """Two scenes of one log 0.2-0.4 s apart: the second continues the first (run.json
    ``continues``), one component, and the run says so."""
    root = sim_dataroot(["schedule.scene_gap_s=[0.2, 0.4]"])
    out = tmp_path / "res"
    result = CliRunner().invoke(
        app,
        ["run", "--dataroot", str(root), "--version", "v1.0-mini", "--out", str(out),
         "--no-loops", "--no-progress"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    run = json.loads((out / "run.json").read_text())
    first, second = run["sessions"]
    assert run["continues"] == {second: first}
    assert run["components"] == [[first, second]]
    assert "1 scene(s) continue the scene before them (same log, back to back): 1 drive(s)" in (
        result.output
    )


def test_run_over_two_cars_reports_each_rigs_calibration(real_dataroot, tmp_path):
    """A Boston and a Singapore scene: each car's mounting estimate, with its scenes, and the
    calibration pass (SLAM's preset) skipped with a warning rather than applied across cars."""
    out = tmp_path / "res"
    result = CliRunner().invoke(
        app,
        ["run", "--dataroot", str(real_dataroot), "--scenes", "scene-0103,scene-0061",
         "--out", str(out), "--no-loops", "--no-progress"],
    )  # fmt: skip
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    rigs = summary["doppler_calibration_by_rig"]
    assert [r["scenes"] for r in rigs] == [["scene-0103"], ["scene-0061"]]
    assert summary["doppler_calibration"] == rigs[1]
    assert "passes" not in summary["doppler_calibration"]


def test_synthetic_dataset_is_generated_once(tmp_path, monkeypatch, capsys):
    from radarslam.sim.generate import SimulationSummary
    from radarslam.slam import commands

    calls = []
    summary = SimulationSummary(
        str(tmp_path / "d"), "v1.0-mini", "demo", 11, 3, 3, 6, 240, 7710, 676688, 47_741_835, 10.9
    )
    monkeypatch.setattr(
        "radarslam.sim.generate.simulate", lambda *a, **k: calls.append(a) or summary
    )
    monkeypatch.setattr("radarslam.sim.generate.is_complete", lambda root, version: bool(calls))
    assert commands.ensure_synthetic("demo", tmp_path / "d", False) == "v1.0-mini"
    assert commands.ensure_synthetic("demo", tmp_path / "d", False) == "v1.0-mini"
    assert len(calls) == 1
    # one line for the user, the same as `radarslam simulate` prints, not the record's repr
    err = capsys.readouterr().err.strip()
    assert err == summary.describe()
    assert err.startswith(f"wrote {tmp_path / 'd'} (v1.0-mini): 3 logs on 3 days, 6 scenes")
    assert "47.7 MB in 10.9 s (707 sweeps/s)" in err


def test_missing_dataroot_is_one_line_error(tmp_path):
    result = CliRunner().invoke(app, ["run", "--out", str(tmp_path / "r")])
    assert result.exit_code != 0
    assert "--dataroot is required" in str(result.exception)


def test_bad_out_fails_before_any_data_is_read(tmp_path):
    from radarslam.errors import DataError

    (tmp_path / "afile").write_text("keep me")
    nowhere = str(tmp_path / "no-dataroot")  # reading it first would fail differently
    for out in (tmp_path / "afile", tmp_path / "afile" / "res"):
        result = CliRunner().invoke(
            app, ["run", "--dataroot", nowhere, "--out", str(out), "--no-progress"]
        )
        assert isinstance(result.exception, DataError), result.output
        assert str(result.exception).startswith(f"{out}: cannot create results folder (")
    assert (tmp_path / "afile").read_text() == "keep me"


def test_max_scenes_must_be_positive(tmp_path):
    import pytest

    from radarslam.errors import ConfigError
    from radarslam.slam.commands import _select_scenes

    for value in ("0", "-1"):
        result = CliRunner().invoke(
            app, ["run", "--dataroot", str(tmp_path), "--out", str(tmp_path / "r"),
                  "--max-scenes", value],
        )  # fmt: skip
        assert result.exit_code == 2 and "--max-scenes" in result.output, result.output

    class Reader:
        dataroot = tmp_path

        def scene(self, name):
            return name

    with pytest.raises(ConfigError, match="--max-scenes 0: must be at least 1"):
        _select_scenes(Reader(), "scene-0001", None, 0)


def test_rerun_with_fewer_scenes_replaces_the_folder(tiny_dataroot, tmp_path):
    out = tmp_path / "res"
    base = ["run", "--dataroot", str(tiny_dataroot), "--version", "v1.0-mini", "--out", str(out),
            "--no-loops", "--no-progress"]  # fmt: skip
    result = CliRunner().invoke(app, base)
    assert result.exit_code == 0, result.output
    assert (out / "poses_scene-0002.tum").is_file() and (out / "metrics.json").is_file()
    assert (out / "plots" / "errors_scene-0002.png").is_file()
    result = CliRunner().invoke(app, [*base, "--max-scenes", "1", "--no-evaluate"])
    assert result.exit_code == 0, result.output
    names = {p.name for p in out.rglob("*")}
    assert not [n for n in names if "scene-0002" in n or n.startswith(".")], names
    assert "metrics.json" not in names and "trajectories.png" not in names
    assert {"run.json", "timing.json", "config.yaml", "poses_scene-0001.tum"} <= names
    assert sorted(p.name for p in tmp_path.iterdir()) == ["res"]
    result = CliRunner().invoke(app, ["eval", str(out), "--no-plots"])
    assert result.exit_code == 0, result.output
    assert list(json.loads((out / "metrics.json").read_text())["per_session"]) == ["scene-0001"]


def test_demo_twice_into_the_same_folder(tmp_path, monkeypatch):
    import numpy as np

    from radarslam.slam import commands
    from radarslam.slam.outputs import SessionResult, write_results

    runs = []

    def fake_run_slam(dataroot, version, out, config=None, progress=True):
        runs.append(out)
        t = np.arange(3, dtype=np.int64)
        write_results(out, [SessionResult("scene-0001", t, np.stack([np.eye(4)] * 3))])

    def fake_data(preset, dataroot, progress):
        dataroot.mkdir(parents=True, exist_ok=True)
        (dataroot / "table.json").write_text("[]")
        return "v1.0-mini"

    monkeypatch.setattr(commands, "run_slam", fake_run_slam)
    monkeypatch.setattr(commands, "ensure_synthetic", fake_data)
    for _ in range(2):
        result = CliRunner().invoke(app, ["demo", "--out", str(tmp_path / "demo"), "--no-progress"])
        assert result.exit_code == 0, result.output
    assert runs == [tmp_path / "demo" / "results"] * 2
    assert sorted(p.name for p in (tmp_path / "demo").iterdir()) == ["data", "results"]
    assert (tmp_path / "demo" / "data" / "table.json").is_file()


def test_run_takes_a_named_preset_or_a_yaml(tiny_dataroot, tmp_path):
    """Every dataroot runs with slam/default.yaml (the odometry's mounting-yaw states on: the
    simulator's units are mounted off their written calibration too); --config names a preset
    or a YAML; the resolved config is written beside the results."""
    import yaml

    def run(out, *extra):
        result = CliRunner().invoke(
            app,
            ["run", "--dataroot", str(tiny_dataroot), "--version", "v1.0-mini", "--out", str(out),
             "--no-loops", "--no-progress", "--no-evaluate", "--max-scenes", "1", *extra],
        )  # fmt: skip
        assert result.exit_code == 0, result.output
        cfg = yaml.safe_load((out / "config.yaml").read_text())
        return cfg["odometry"]["fusion"]["calibration"]["yaw_bias_model"]

    assert run(tmp_path / "a") == "mounting"
    own = tmp_path / "own.yaml"
    own.write_text("odometry:\n  fusion:\n    calibration:\n      yaw_bias_model: none\n")
    assert run(tmp_path / "b", "--config", str(own)) == "none"
    result = CliRunner().invoke(
        app,
        ["run", "--dataroot", str(tiny_dataroot), "--version", "v1.0-mini", "--out",
         str(tmp_path / "c"), "--no-loops", "--config", "synthetic"],
    )  # fmt: skip
    # (the console entry point turns this into one line and exit status 2)
    assert "synthetic: config file does not exist" in str(result.exception)
