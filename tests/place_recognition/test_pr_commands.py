"""The ``radarslam pr`` CLI end to end on the mini dataroot (untrained compact network)."""

import json

import pytest
import torch
import yaml
from typer.testing import CliRunner

from radarslam.cli import app

runner = CliRunner()


@pytest.fixture(scope="module")
def untrained_checkpoint(tmp_path_factory):
    from radarslam.place_recognition.checkpoint import save_checkpoint
    from radarslam.place_recognition.models import build_model, load_model_config

    torch.manual_seed(0)
    cfg = load_model_config("compact_se_te").model_copy(update={"seq_len": 2})
    path = tmp_path_factory.mktemp("ckpt") / "untrained.pt"
    return save_checkpoint(path, build_model(cfg), cfg)


def invoke(args):
    res = runner.invoke(app, args, catch_exceptions=False)
    assert res.exit_code == 0, res.output
    return res.output


def test_prepare_eval_builddb_query(mini_dataroot, mini_config, untrained_checkpoint, tmp_path):
    cfg = mini_config(mini_dataroot)
    cfg_path = tmp_path / "data_mini.yaml"
    cfg_path.write_text(yaml.safe_dump(cfg.model_dump(mode="json")))
    out = invoke(["pr", "prepare", str(cfg_path), "--out", str(tmp_path / "cache")])
    assert "prepared" in out and "| database |" in out
    prepared = tmp_path / "cache" / "mini"
    out = invoke(["pr", "eval", str(prepared), "--baseline", "m2dp", "--out", str(tmp_path / "ev")])
    assert "M2DP+RCSHR" in out
    rows = json.loads((tmp_path / "ev" / "M2DP_test.json").read_text())["rows"]
    assert [r["method"] for r in rows] == ["M2DP", "M2DP+RCSHR"]
    out = invoke(["pr", "eval", str(prepared), "--checkpoint", str(untrained_checkpoint),
                  "--no-rerank", "--out", str(tmp_path / "ev")])  # fmt: skip
    assert "compact_se_te" in out
    db = tmp_path / "db.npz"
    rcfg = tmp_path / "rec.yaml"
    rcfg.write_text("seq_len: 2\n")
    out = invoke(["pr", "build-db", "--dataroot", str(mini_dataroot), "--version", "v1.0-mini",
                  "--scenes", "scene-0001,scene-0002", "--checkpoint",
                  str(untrained_checkpoint), "--config", str(rcfg), "--out", str(db)])  # fmt: skip
    assert "10 places" in out
    out = invoke(["pr", "query", str(db), "--dataroot", str(mini_dataroot), "--version",
                  "v1.0-mini", "--scenes", "scene-0002", "-k", "2"])  # fmt: skip
    lines = [ln for ln in out.splitlines() if ln.strip()]
    assert len(lines) == 6 and all("(d=" in ln for ln in lines)
    # a frame queried against a database that holds it finds itself
    first = lines[0].split(":")[0]
    assert lines[0].split(": ")[1].startswith(f"{first} (d=0.000")


def test_cli_errors(tmp_path):
    from radarslam.errors import ConfigError, DataError

    with pytest.raises(ConfigError, match="exactly one"):
        runner.invoke(app, ["pr", "eval", str(tmp_path)], catch_exceptions=False)
    with pytest.raises(DataError, match="does not exist"):
        runner.invoke(app, ["pr", "eval", str(tmp_path / "x"), "--baseline", "m2dp"],
                      catch_exceptions=False)  # fmt: skip


def _raises(exc_type, message, args):
    with pytest.raises(exc_type, match=message):
        runner.invoke(app, args, catch_exceptions=False)


def test_cli_checks_outputs_and_options_up_front(tmp_path):
    """Each of these fails at once, before any data, checkpoint or database is read."""
    from radarslam.errors import CheckpointError, ConfigError

    afile = tmp_path / "afile"
    afile.write_text("x")
    nothing = str(tmp_path / "no_such_cache")
    build = ["pr", "build-db", "--dataroot", nothing, "--scenes", "scene-0001", "--out"]
    _raises(ConfigError, "output file is an existing directory", [*build, str(tmp_path)])
    _raises(ConfigError, "afile: output directory is an existing file",
            [*build, str(afile / "db.npz")])  # fmt: skip
    _raises(ConfigError, "afile: output directory is an existing file",
            ["pr", "eval", nothing, "--baseline", "m2dp", "--out", str(afile)])  # fmt: skip
    _raises(ConfigError, "afile: output directory is an existing file",
            ["pr", "train", nothing, "--out", str(afile)])  # fmt: skip
    _raises(ConfigError, "afile: output directory is an existing file",
            ["pr", "prepare", nothing, "--out", str(afile)])  # fmt: skip
    _raises(ConfigError, r"--jobs -2: must be >= 1",
            ["pr", "prepare", nothing, "--jobs", "-2", "--out", str(tmp_path)])  # fmt: skip
    for split in ("database", "train"):
        _raises(ConfigError, f"--split '{split}': choose one of val, test",
                ["pr", "eval", nothing, "--baseline", "m2dp", "--split", split])  # fmt: skip
    _raises(ConfigError, "-k 0: must be >= 1",
            ["pr", "query", str(tmp_path / "none.npz"), "--dataroot", nothing, "--scenes", "s",
             "-k", "0"])  # fmt: skip
    # a previous run's checkpoints are neither mixed with a new run's nor silently replaced
    run = tmp_path / "run"
    run.mkdir()
    (run / "best.pt").write_bytes(b"old")
    _raises(ConfigError, r"run: holds a previous run \(best\.pt\); pass --resume .* --overwrite",
            ["pr", "train", nothing, "--out", str(run)])  # fmt: skip
    _raises(CheckpointError, r"last\.pt: nothing to resume",
            ["pr", "train", nothing, "--out", str(run), "--resume"])  # fmt: skip
    _raises(ConfigError, "not both",
            ["pr", "train", nothing, "--out", str(run), "--resume", "--overwrite"])  # fmt: skip
    # with --overwrite the run goes on (and fails here on the missing cache, not on OUT)
    from radarslam.errors import DataError

    _raises(DataError, "no_such_cache: prepared directory does not exist",
            ["pr", "train", nothing, "--out", str(run), "--overwrite"])  # fmt: skip
