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


def test_synthetic_dataset_is_generated_once(tmp_path, monkeypatch):
    from radarslam.slam import commands

    calls = []
    monkeypatch.setattr(
        "radarslam.sim.generate.simulate", lambda *a, **k: calls.append(a) or "generated"
    )
    monkeypatch.setattr("radarslam.sim.generate.is_complete", lambda root, version: bool(calls))
    assert commands._ensure_synthetic("demo", tmp_path / "d", False) == "v1.0-mini"
    assert commands._ensure_synthetic("demo", tmp_path / "d", False) == "v1.0-mini"
    assert len(calls) == 1


def test_missing_dataroot_is_one_line_error(tmp_path):
    result = CliRunner().invoke(app, ["run", "--out", str(tmp_path / "r")])
    assert result.exit_code != 0
    assert "--dataroot is required" in str(result.exception)
