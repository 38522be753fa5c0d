import json

import numpy as np
import pytest
import yaml

from radarslam.errors import ConfigError, DataError
from radarslam.place_recognition.config import PrepareConfig
from radarslam.place_recognition.dataset import load_prepared
from radarslam.place_recognition.image import rasterise
from radarslam.place_recognition.prepare import prepare


def test_prepared_contents(mini_prepared):
    data = load_prepared(mini_prepared)
    n = len(data)
    assert n == 16 and data.images.shape == (n, 200, 200) and data.images.dtype == np.uint8
    assert set(np.unique(data.images)) <= {0, 1}
    # resolved config written next to the artefacts
    cfg = PrepareConfig.model_validate(yaml.safe_load((mini_prepared / "config.yaml").read_text()))
    assert cfg.name == "mini" and cfg.image.size_px == 200 and cfg.accumulation.nsweeps == 7
    # scenes in time order, frames contiguous; sequences stay inside a scene, oldest first
    assert list(dict.fromkeys(data.scene_names)) == ["scene-0001", "scene-0002", "scene-0004"]
    assert np.all(np.diff(data.timestamps_us) > 0)
    seq = data.sequences
    assert seq.shape == (n, 2) and np.all(seq[:, 1] == np.arange(n))
    assert np.all(data.scene_names[seq[:, 0]] == data.scene_names)
    # the image is the rasterised stored points (stored at 1 cm: a point within 5 mm of a pixel
    # border may land in the neighbour pixel); RCS in [0, 1] per frame
    for i in (0, 7, 15):
        again = rasterise(data.points_xy[i], cfg.image)[0]
        assert np.sum(again != data.images[i]) <= 0.02 * data.images[i].sum()
        assert data.rcs[i].min() == 0.0 and data.rcs[i].max() == 1.0
        assert len(data.rcs[i]) == len(data.points_xy[i]) > 100
    # split: the later day is held out, every query has a DB frame within 9 m
    db = data.splits["database"]
    held = np.concatenate([data.splits["val"], data.splits["test"]])
    assert len(db) > 0 and len(held) > 0
    assert set(data.scene_names[held]) == {"scene-0004"}
    for q in held:
        assert len(data.positives(q)) > 0
    counts = json.loads((mini_prepared / "split.json").read_text())
    assert counts["database"] == len(db)
    stats = json.loads((mini_prepared / "dpr.json").read_text())
    assert stats["sweeps"] > 400 and 0 < stats["removed_fraction"] < 0.2
    # compact: bit-packed images
    assert (mini_prepared / "images.npz").stat().st_size < 16 * 200 * 200 / 8 + 20_000


def test_cache_skip_and_overwrite(mini_dataroot, mini_config, tmp_path):
    cfg = mini_config(mini_dataroot)
    stages = []
    root = prepare(cfg, tmp_path, progress=False, on_stage=stages.append)
    assert stages == ["frames", "clouds", "split"]
    mtime = (root / "images.npz").stat().st_mtime_ns
    stages.clear()
    prepare(cfg, tmp_path, progress=False, on_stage=stages.append)
    assert stages == [] and (root / "images.npz").stat().st_mtime_ns == mtime
    changed = cfg.model_copy(update={"split": cfg.split.model_copy(update={"seed": 7})})
    with pytest.raises(ConfigError, match=r"split\.npz"):
        prepare(changed, tmp_path, progress=False)
    stages.clear()
    prepare(changed, tmp_path, progress=False, overwrite=True, on_stage=stages.append)
    assert stages == ["frames", "clouds", "split"]
    assert yaml.safe_load((root / "config.yaml").read_text())["split"]["seed"] == 7


def test_dpr_off_keeps_more_points(mini_dataroot, mini_config, mini_prepared, tmp_path):
    cfg = mini_config(mini_dataroot, name="mini_nodpr", dpr={"enabled": False})
    no_dpr = load_prepared(prepare(cfg, tmp_path, progress=False))
    with_dpr = load_prepared(mini_prepared)
    n_no = sum(len(r) for r in no_dpr.rcs)
    n_with = sum(len(r) for r in with_dpr.rcs)
    assert n_with < n_no
    # the split depends on poses only
    for k in ("database", "train", "val", "test"):
        np.testing.assert_array_equal(no_dpr.splits[k], with_dpr.splits[k])


def test_prepare_errors(tmp_path, mini_dataroot, mini_config):
    with pytest.raises(ConfigError, match="dataroot"):
        prepare(PrepareConfig(source={"dataroot": None}), tmp_path, progress=False)
    bad = mini_config(mini_dataroot, source={"dataroot": str(mini_dataroot),
                                                      "versions": ["v1.0-trainval"]})  # fmt: skip
    with pytest.raises(DataError, match=r"v1\.0-trainval"):
        prepare(bad, tmp_path, progress=False)
    with pytest.raises(DataError, match="does not exist"):
        load_prepared(tmp_path / "nope")
    # one scene is one capture day: the held-out days would be all of them, said before the
    # clouds are accumulated
    one_day = mini_config(mini_dataroot, name="one_day")
    one_day = one_day.model_copy(
        update={"source": one_day.source.model_copy(update={"max_scenes": 1})}
    )
    stages: list[str] = []
    with pytest.raises(DataError, match=r"only 1 capture day\(s\)"):
        prepare(one_day, tmp_path, progress=False, on_stage=stages.append)
    assert stages == ["frames"]


def test_parallel_clouds_identical(mini_dataroot, mini_config, mini_prepared, tmp_path):
    cfg = mini_config(mini_dataroot)
    par = prepare(cfg, tmp_path, progress=False, jobs=2)
    for name in ("images.npz", "points.npz"):
        a, b = np.load(mini_prepared / name), np.load(par / name)
        for k in a.files:
            np.testing.assert_array_equal(a[k], b[k])
    assert json.loads((par / "dpr.json").read_text()) == json.loads(
        (mini_prepared / "dpr.json").read_text()
    )


def test_damaged_stage_files_are_recomputed(mini_dataroot, mini_config, tmp_path):
    cfg = mini_config(mini_dataroot)
    root = prepare(cfg, tmp_path, progress=False)
    # a truncated points.npz (images.npz intact) and a garbled split.json
    blob = (root / "points.npz").read_bytes()
    (root / "points.npz").write_bytes(blob[: len(blob) // 3])
    (root / "split.json").write_bytes(b'{"database": 1\x00')
    stages = []
    prepare(cfg, tmp_path, progress=False, on_stage=stages.append)
    assert stages == ["clouds", "split"]
    data = load_prepared(root)
    assert len(data.rcs) == len(data) == 16
    assert json.loads((root / "split.json").read_text())["frames"] == 16


def test_failed_prepare_leaves_no_mixed_cache(mini_dataroot, mini_config, mini_prepared, tmp_path):
    import shutil

    # a fresh directory: nothing is written, not even config.yaml
    source = {"dataroot": str(mini_dataroot), "versions": ["v1.0-mini"], "location": "mars"}
    mars = mini_config(mini_dataroot, source=source)
    with pytest.raises(DataError, match="no scene at location 'mars'"):
        prepare(mars, tmp_path / "fresh", progress=False)
    assert not (tmp_path / "fresh" / "mini").exists()
    # --overwrite of a complete cache with a config that fails: the old stages are gone and the
    # old config.yaml stays, so the directory can never be loaded as a mix of two configs
    root = tmp_path / "cache" / "mini"
    shutil.copytree(mini_prepared, root)
    before = (root / "config.yaml").read_text()
    with pytest.raises(DataError, match="mars"):
        prepare(mars, tmp_path / "cache", progress=False, overwrite=True)
    assert (root / "config.yaml").read_text() == before
    assert sorted(p.name for p in root.iterdir()) == ["config.yaml"]
    with pytest.raises(DataError, match=r"frames\.npz: missing"):
        load_prepared(root)


def test_prepare_output_and_jobs_errors(mini_dataroot, mini_config, tmp_path):
    cfg = mini_config(mini_dataroot)
    (tmp_path / "afile").write_text("x")
    with pytest.raises(ConfigError, match="afile: output directory is an existing file"):
        prepare(cfg, tmp_path / "afile", progress=False)
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "mini").write_text("x")
    with pytest.raises(ConfigError, match=r"mini: output directory is an existing file"):
        prepare(cfg, tmp_path / "out", progress=False)
    with pytest.raises(ConfigError, match="jobs=0"):
        prepare(cfg, tmp_path, progress=False, jobs=0)
