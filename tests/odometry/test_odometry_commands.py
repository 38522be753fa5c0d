"""``radarslam odometry`` command plumbing: a bad --out fails before any data is read."""

from __future__ import annotations

import numpy as np
from typer.testing import CliRunner

from radarslam.cli import app
from radarslam.errors import DataError


def test_bad_out_fails_before_reading_data(tmp_path):
    (tmp_path / "afile").write_text("keep me")
    nowhere = str(tmp_path / "no-dataroot")  # reading it first would fail differently
    for out in (tmp_path / "afile", tmp_path / "afile" / "sub"):
        result = CliRunner().invoke(
            app, ["odometry", "--dataroot", nowhere, "--out", str(out), "--no-progress"]
        )
        assert isinstance(result.exception, DataError), result.output
        assert str(result.exception) == (
            f"{out}: cannot create results folder ({tmp_path / 'afile'} is a file, not a folder)"
        )
    assert (tmp_path / "afile").read_text() == "keep me"


def test_override_errors_name_the_override(tmp_path):
    result = CliRunner().invoke(
        app,
        ["odometry", "--dataroot", str(tmp_path), "--out", str(tmp_path / "o"),
         "--set", "registration.voxel_size_m=-1"],
    )  # fmt: skip
    msg = str(result.exception)
    assert msg.startswith("override 'registration.voxel_size_m=-1': 'registration.voxel_size_m'")
    assert "default.yaml" not in msg
    assert not (tmp_path / "o").exists()


def test_outputs_replace_an_earlier_run_as_a_whole(tiny_dataroot, tmp_path, monkeypatch):
    from radarslam.nuscenes.reader import NuScenesRadar

    out = tmp_path / "odo"
    names = [s.name for s in NuScenesRadar(tiny_dataroot, "v1.0-mini").scenes()]
    args = ["odometry", "--dataroot", str(tiny_dataroot), "--out", str(out), "--no-progress"]
    assert CliRunner().invoke(app, args).exit_code == 0
    assert sorted(p.name for p in out.glob("gt_*.tum")) == sorted(f"gt_{n}.tum" for n in names)
    # a re-run over one scene leaves no file of the other
    result = CliRunner().invoke(app, [*args, "--scenes", names[0]])
    assert result.exit_code == 0, result.output
    s = names[0]
    assert sorted(p.name for p in out.iterdir()) == sorted(
        ["config.yaml", "run.json", "summary.json", f"key_frames_{s}.csv"]
        + [f"{stem}_{s}.{ext}" for stem in ("gt", "odometry") for ext in ("kitti", "tum")]
    )
    before = (out / "summary.json").read_text()

    # a run that fails while writing keeps the previous folder and leaves no temporary one
    import radarslam.odometry.run as run_module

    def boom(*_args, **_kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(run_module, "_key_frames_csv", boom)
    result = CliRunner().invoke(app, args)
    assert result.exit_code != 0
    assert (out / "summary.json").read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["odo"]


def test_a_folder_holding_other_things_is_not_replaced(tmp_path):
    out = tmp_path / "odo"
    out.mkdir()
    (out / "odometry_scene-0001.tum").write_text("")
    (out / "notes.txt").write_text("mine")
    nowhere = str(tmp_path / "no-dataroot")
    result = CliRunner().invoke(
        app, ["odometry", "--dataroot", nowhere, "--out", str(out), "--no-progress"]
    )
    assert isinstance(result.exception, DataError)
    assert str(result.exception).startswith(f"{out}: holds 'notes.txt', which is not a result file")
    assert (out / "notes.txt").read_text() == "mine"


def test_run_odometry_scene_arguments(tiny_dataroot):
    import pytest

    from radarslam.errors import ConfigError
    from radarslam.nuscenes.reader import NuScenesRadar
    from radarslam.odometry.run import run_odometry

    reader = NuScenesRadar(tiny_dataroot, "v1.0-mini")
    name = reader.scenes()[0].name
    one = run_odometry(reader, name, progress=False, max_frames_per_scene=4)  # not per character
    assert len(one) == 4 and set(one.scene_names) == {name}
    info = run_odometry(reader, reader.scene(name), progress=False, max_frames_per_scene=4)
    assert np.array_equal(info.poses, one.poses)
    with pytest.raises(DataError, match=f"scene '{name}' is given more than once"):
        run_odometry(reader, [name, reader.scene(name)], progress=False)
    with pytest.raises(DataError, match="run_odometry: no scene given"):
        run_odometry(reader, [], progress=False)
    for bad in (0, -3, 2.5):
        with pytest.raises(ConfigError, match=f"max_frames_per_scene must be .*got {bad!r}"):
            run_odometry(reader, name, progress=False, max_frames_per_scene=bad)


def test_eval_reads_the_odometry_folder(tiny_dataroot, tmp_path):
    import json

    out = tmp_path / "odo"
    args = ["odometry", "--dataroot", str(tiny_dataroot), "--out", str(out), "--no-progress"]
    result = CliRunner().invoke(app, [*args, "--method", "doppler"])
    assert result.exit_code == 0, result.output
    run = json.loads((out / "run.json").read_text())
    assert run["kind"] == "odometry" and run["method"] == "doppler"
    summary = json.loads((out / "summary.json").read_text())
    assert run["sessions"] == list(summary["scenes"])

    result = CliRunner().invoke(app, ["eval", str(out), "--no-plots"])
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["kind"] == "odometry" and metrics["method"] == "doppler"
    assert metrics["loops"] is None and set(metrics["run"]) == {"odometry"}
    for scene, numbers in summary["scenes"].items():
        per_kind = metrics["per_session"][scene]
        assert set(per_kind) == {"odometry"}  # no SLAM rows
        assert per_kind["odometry"]["num_poses"] == numbers["frames"]
        # every frame, one segment per scene: eval's ATE is the run's own
        assert np.isclose(per_kind["odometry"]["ate_rmse_m"], numbers["ate_rmse_m"], rtol=1e-6)
    # eval's files belong to the folder: a re-run replaces it
    assert CliRunner().invoke(app, args).exit_code == 0
    assert not (out / "metrics.json").exists()


def test_the_calibration_is_printed_as_summary_json_holds_it():
    from radarslam.odometry.commands import calibration_line

    cal = {
        "yaw_bias_model": "mounting",
        "radar_speed_scale_error": -0.003,
        "rig": "abc",
        "scenes": ["scene-0916"],
        "mounting_yaw_error_deg": {"RADAR_FRONT": -0.322, "RADAR_BACK_LEFT": 1.283},
        "mounting_yaw_sigma_deg": {"RADAR_FRONT": 0.233, "RADAR_BACK_LEFT": 0.22},
        "speed_scale_error": 0.0012,
        "speed_scale_sigma": 0.0004,
    }
    assert calibration_line(cal) == (
        "Doppler calibration (scene-0916): mounting yaw error (deg) FRONT -0.32 +- 0.23; "
        "BACK_LEFT +1.28 +- 0.22; radar speed scale error -0.003 (configured; +0.0012 +- 0.0004 "
        "left)"
    )
    assert calibration_line({**cal, "speed_scale_sigma": 0.0}).endswith("-0.003 (configured)")
    assert calibration_line({"yaw_bias_model": "none"}) is None
    assert calibration_line(None) is None


def test_the_command_prints_the_calibration(tiny_dataroot, tmp_path):
    args = ["odometry", "--dataroot", str(tiny_dataroot), "--out", str(tmp_path / "o")]
    result = CliRunner().invoke(app, [*args, "--no-progress"])
    assert result.exit_code == 0, result.output
    lines = result.output.splitlines()
    assert any(ln.startswith("ours: ") and "drift per 100 m" in ln for ln in lines), lines
    assert any(ln.startswith("Doppler calibration") for ln in lines), lines
