"""``radarslam odometry`` command plumbing: a bad --out fails before any data is read."""

from __future__ import annotations

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
