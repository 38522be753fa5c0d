"""Compact, lazy radar tables: content, streaming parser, on-disk cache, and bad tables."""

from __future__ import annotations

import json
import logging
import os
import re

import numpy as np
import pytest
from mini_dataroot import VERSION, tok

from radarslam.errors import DataError
from radarslam.nuscenes import json_stream
from radarslam.nuscenes.tables import NuScenesTables, TokenIndex
from radarslam.types import RADAR_CHANNELS


def test_radar_index_content(mini):
    t = NuScenesTables(mini.dataroot, VERSION, use_cache=False)
    radar = t.radar
    all_tokens = [tok for toks in mini.sweeps.values() for tok in toks]
    assert len(radar) == len(all_tokens) == 769  # pinned: 4 scenes x 5 radars, one gap
    assert sorted(radar.token.astype(str)) == sorted(all_tokens)  # lidar records skipped
    for i in (0, 17, 500, len(radar) - 1):
        tok = radar.token[i].decode()
        w_from_s = t.world_from_ego(i) @ t.ego_from_sensor(int(radar.calibrated_sensor[i]))
        np.testing.assert_allclose(w_from_s, mini.world_from_sensor[tok], atol=1e-9)
        ch = RADAR_CHANNELS[radar.channel[i]]
        assert f"/{ch}/" in radar.filename[i].decode()
    # chains: every next's prev is the record itself
    has_next = radar.next >= 0
    assert (radar.prev[radar.next[has_next]] == np.flatnonzero(has_next)).all()
    assert int((radar.prev < 0).sum()) == 20  # one chain head per scene and radar
    assert radar.nbytes < 300 * len(radar)  # compact: no Python object per record


@pytest.mark.parametrize("compact", [False, True])
def test_streaming_parser_is_chunk_and_whitespace_independent(mini, clone, monkeypatch, compact):
    ref = NuScenesTables(mini.dataroot, VERSION, use_cache=False).radar
    root = clone()
    for name in ("sample_data", "ego_pose"):
        p = root / VERSION / f"{name}.json"
        recs = json.loads(p.read_text())
        text = json.dumps(recs, separators=(",", ":")) if compact else json.dumps(recs, indent=4)
        p.write_text(text)
    monkeypatch.setattr(json_stream, "_CHUNK_BYTES", 97)  # records straddle every chunk boundary
    got = NuScenesTables(root, VERSION, use_cache=False).radar
    for name, arr in ref.arrays().items():
        np.testing.assert_array_equal(getattr(got, name), arr, err_msg=name)


def test_cache_roundtrip_and_invalidation(mini, tmp_path, caplog):
    cache = tmp_path / "cache"
    kw = {"use_cache": True, "cache_dir": cache, "cache_min_bytes": 0}
    first = NuScenesTables(mini.dataroot, VERSION, **kw)
    ref = first.radar
    assert first.cache_hit is False
    files = list(cache.glob("*.npz"))
    assert len(files) == 1 and not list(mini.dataroot.rglob("*.npz"))
    second = NuScenesTables(mini.dataroot, VERSION, **kw)
    got = second.radar
    assert second.cache_hit is True
    for name, arr in ref.arrays().items():
        np.testing.assert_array_equal(getattr(got, name), arr, err_msg=name)
    # a damaged cache is rebuilt with a warning, never fatal
    files[0].write_bytes(b"not a zip")
    third = NuScenesTables(mini.dataroot, VERSION, **kw)
    assert len(third.radar) == len(ref) and third.cache_hit is False
    assert "ignoring unreadable radar index cache" in caplog.text
    # below the size threshold nothing is written
    cache2 = tmp_path / "cache2"
    NuScenesTables(mini.dataroot, VERSION, use_cache=True, cache_dir=cache2).radar  # noqa: B018
    assert not cache2.exists()


def test_cache_key_follows_the_tables(mini, clone, tmp_path):
    root = clone()
    kw = {"use_cache": True, "cache_dir": tmp_path / "c", "cache_min_bytes": 0}
    before = NuScenesTables(root, VERSION, **kw)
    sd = mini.sweeps[("scene-0003", "RADAR_FRONT")][0]
    row = before.radar_tokens.find(sd)
    x0 = before.radar.ego_translation[row, 0]
    p = root / VERSION / "ego_pose.json"
    recs = json.loads(p.read_text())
    next(r for r in recs if r["token"] == tok("ego", sd))["translation"][0] += 100.0
    p.write_text(json.dumps(recs, indent=0))
    st = p.stat()
    os.utime(p, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    after = NuScenesTables(root, VERSION, **kw)
    assert after.radar.ego_translation[row, 0] == pytest.approx(x0 + 100.0)
    assert after.cache_hit is False and len(list((tmp_path / "c").glob("*.npz"))) == 2


def test_token_index():
    toks = np.array([b"b", b"a", b"c"])
    idx = TokenIndex(toks)
    assert idx.find("a") == 1 and idx.find("c") == 2 and idx.find("zz") == -1
    assert idx.find("\u00e9") == -1
    assert idx.find_many(np.array([b"c", b"x", b"b"])).tolist() == [2, -1, 0]
    with pytest.raises(DataError, match="appears more than once"):
        TokenIndex(np.array([b"a", b"b", b"a"]), what="sample_data.json")


# ---- bad input -------------------------------------------------------------------------------
def test_missing_dataroot_and_version(mini, tmp_path):
    with pytest.raises(DataError, match="dataroot does not exist"):
        NuScenesTables(tmp_path / "nope")
    with pytest.raises(DataError, match=r"unknown nuScenes version 'v2\.0'"):
        NuScenesTables(mini.dataroot, "v2.0")
    with pytest.raises(DataError, match=r"v1.0-trainval: version folder is missing \(present"):
        NuScenesTables(mini.dataroot, "v1.0-trainval")
    with pytest.raises(DataError, match="pass the folder above it as the dataroot"):
        NuScenesTables(mini.dataroot / VERSION, VERSION)


def test_missing_table(clone):
    root = clone()
    (root / VERSION / "ego_pose.json").unlink()
    with pytest.raises(DataError, match=r"ego_pose\.json: table file is missing"):
        NuScenesTables(root, VERSION)


def _damage(root, name, fn):
    p = root / VERSION / f"{name}.json"
    p.write_bytes(fn(p.read_bytes()))


@pytest.mark.parametrize(
    ("name", "fn", "match"),
    [
        ("scene", lambda b: b[: len(b) // 2], r"scene\.json: corrupt JSON \(line"),
        ("log", lambda b: b'{"a": 1}', r"log\.json: expected a JSON list"),
        ("sample", lambda b: b"[1, 2]", r"sample\.json: record 0 is a number, expected an object"),
        (
            "sample_data",
            lambda b: b"null",
            r"sample_data\.json: expected a JSON list of records, got null",
        ),
        ("ego_pose", lambda b: b"[1, 2, 3]", r"ego_pose\.json: record 0 is a number, expected an"),
        (
            "sample_data",
            lambda b: b"[[1]," + b[1:],
            r"sample_data\.json: record 0 is a list, expected",
        ),
        (
            "sample_data",
            lambda b: b[: len(b) - 300],
            r"sample_data\.json: corrupt JSON \(truncated",
        ),
        ("sample_data", lambda b: b.replace(b"},", b"} x,", 1), r"sample_data\.json: corrupt JSON"),
        ("sample_data", lambda b: b.replace(b"},", b"}", 1), r"sample_data\.json: corrupt JSON"),
        ("ego_pose", lambda b: b"{" + b, r"ego_pose\.json: corrupt JSON"),
        ("ego_pose", lambda b: b[1:], r"ego_pose\.json: corrupt JSON \(expected '\['"),
        ("ego_pose", lambda b: b + b"]", r"ego_pose\.json: corrupt JSON \(unexpected"),
        ("sample_data", lambda b: b.replace(b'"timestamp"', b'"ts"'), r"has no 'timestamp' field"),
        ("sample_data", lambda b: b.replace(b'"pcd"', b"pcd"), r"corrupt JSON in the record"),
        ("calibrated_sensor", lambda b: b.replace(b'"rotation"', b'"rot"'), r"has no 'rotation'"),
    ],
)
def test_corrupt_tables(clone, name, fn, match):
    root = clone()
    _damage(root, name, fn)
    t = NuScenesTables(root, VERSION, use_cache=False)
    with pytest.raises(DataError, match=match) as exc:
        _ = t.radar
    assert "\n" not in str(exc.value)


def _edit_records(root, name, edit):
    p = root / VERSION / f"{name}.json"
    recs = json.loads(p.read_text())
    edit(recs)
    p.write_text(json.dumps(recs, indent=0))


def _radar(recs):
    return next(r for r in recs if "RADAR_" in r.get("filename", "RADAR_"))


@pytest.mark.parametrize(
    ("name", "edit", "match"),
    [
        (
            "sample_data",
            lambda rs: _radar(rs).update(sample_token="x"),
            "sample_token 'x' is not in",
        ),
        (
            "sample_data",
            lambda rs: _radar(rs).update(next="x"),
            r"sample_data 'x' \(the next of radar record '\w+'\) is not in sample_data\.json",
        ),
        ("sample_data", lambda rs: _radar(rs).update(timestamp=1.5), "timestamp 1.5 is not an int"),
        ("sample_data", lambda rs: _radar(rs).update(calibrated_sensor_token="q"), "'q' is not in"),
        (
            "ego_pose",
            lambda rs: rs.pop(-1),
            r"ego_pose\.json: ego pose '\w+', named by radar sample_data '\w+' of "
            r"sample_data\.json, is missing \(1 missing in all\)",
        ),
        ("ego_pose", lambda rs: rs[-1].update(rotation=[0, 0, 0, 0]), "zero rotation quaternion"),
        ("ego_pose", lambda rs: rs[-1].update(translation=[1, 2]), "expected 3 numbers"),
        ("sample", lambda rs: rs[0].update(scene_token="s"), "refers to scene 's'"),
        ("scene", lambda rs: rs[0].update(log_token="l"), "refers to log 'l'"),
        ("scene", lambda rs: rs[1].update(name=rs[0]["name"]), "appears twice"),
        # a token or name of the wrong type: named with its table, not a TypeError as a dict key
        ("scene", lambda rs: rs[0].update(name=5), r"scene\.json: record '\w+' field 'name' is 5"),
        ("scene", lambda rs: rs[0].update(token=[1]), r"record 0 field 'token' is \[1\], expected"),
        ("scene", lambda rs: rs[0].update(log_token=[1]), r"field 'log_token' is \[1\], expected"),
        ("sample", lambda rs: rs[0].update(token=5), r"sample\.json: record 0 field 'token' is 5"),
        ("sample", lambda rs: rs[0].update(next=[1]), r"field 'next' is \[1\], expected a string"),
        ("log", lambda rs: rs[0].update(token=[1]), r"log\.json: record 0 field 'token' is \[1\]"),
        ("log", lambda rs: rs[0].update(location=None), r"field 'location' is None, expected a"),
        ("sensor", lambda rs: rs[0].update(token=[1]), r"sensor\.json: record 0 field 'token'"),
        ("sensor", lambda rs: [r.update(channel=1) for r in rs], r"field 'channel' is 1, expected"),
        (
            "calibrated_sensor",
            lambda rs: rs[0].update(sensor_token=[5]),
            r"calibrated_sensor\.json: record '\w+' field 'sensor_token' is \[5\], expected",
        ),
        (
            "sample_data",
            lambda rs: _radar(rs).update(calibrated_sensor_token=[5]),
            r"sample_data\.json: record '\w+' field 'calibrated_sensor_token' is \[5\]",
        ),
        (
            "sample_data",
            lambda rs: _radar(rs).update(sample_token=[5]),
            r"sample_data\.json: record '\w+' field 'sample_token' is \[5\], expected a string",
        ),
        (
            "sample_data",
            lambda rs: [r.update(ego_pose_token=5) for r in rs],
            "a radar record has ego_pose_token 5, expected a string",
        ),
    ],
)
def test_inconsistent_tables(clone, name, edit, match):
    root = clone()
    _edit_records(root, name, edit)
    t = NuScenesTables(root, VERSION, use_cache=False)
    with pytest.raises(DataError, match=match):
        _ = t.radar


# ---- scenes and their samples ------------------------------------------------------------------
def _move_samples(root, src: int, dst: int) -> tuple[str, str]:
    """Reassign every sample of scene.json record ``src`` to scene ``dst``; (name, first token)."""
    scenes = json.loads((root / VERSION / "scene.json").read_text())
    a, b = scenes[src]["token"], scenes[dst]["token"]
    _edit_records(
        root, "sample", lambda rs: [r.update(scene_token=b) for r in rs if r["scene_token"] == a]
    )
    return scenes[src]["name"], scenes[src]["first_sample_token"]


def test_scene_without_samples_is_an_error(clone):
    root = clone()
    name, first = _move_samples(root, 1, 0)
    t = NuScenesTables(root, VERSION, use_cache=False)
    with pytest.raises(DataError) as exc:
        t.check_scene(t.small.scene_row[name])
    msg = str(exc.value)
    assert msg.startswith(str(root / VERSION / "scene.json"))
    assert f"scene {name!r} has no samples" in msg and f"first_sample_token {first!r}" in msg
    assert "belongs to scene" in msg and "\n" not in msg


@pytest.mark.parametrize("key", ["first_sample_token", "last_sample_token"])
def test_scene_first_or_last_sample_of_another_scene(clone, key):
    root = clone()
    scenes = json.loads((root / VERSION / "scene.json").read_text())
    other = scenes[0][key]
    _edit_records(root, "scene", lambda rs: rs[1].update({key: other}))
    t = NuScenesTables(root, VERSION, use_cache=False)
    match = f"scene {scenes[1]['name']!r} {key} {other!r} belongs to scene {scenes[0]['name']!r}"
    with pytest.raises(DataError, match=match):
        t.check_scene(1)


def test_scene_with_empty_first_sample_token(clone):
    root = clone()
    _edit_records(root, "scene", lambda rs: rs[2].update(first_sample_token=""))
    t = NuScenesTables(root, VERSION, use_cache=False)
    with pytest.raises(DataError, match=r"scene 'scene-\d+' first_sample_token is empty"):
        t.check_scene(2)


def test_a_broken_scene_fails_only_when_asked_for(clone):
    from radarslam.nuscenes.reader import NuScenesRadar

    root = clone()
    name, _ = _move_samples(root, 1, 0)
    reader = NuScenesRadar(root, VERSION, use_cache=False)
    assert name in [s.name for s in reader.scenes()]  # listed, with the others
    with pytest.raises(DataError, match=f"scene {name!r} has no samples"):
        reader.scene(name)
    with pytest.raises(DataError, match=f"scene {name!r} has no samples"):
        list(reader.iter_frames(reader.scenes()[1]))
    # the scene that took its samples is longer now; another one is read as before
    untouched = json.loads((root / VERSION / "scene.json").read_text())[2]["name"]
    assert len(list(reader.iter_frames(untouched))) > 0


# ---- a neighbour that is not a radar record: the message names the real cause --------------------
def _middle_radar(recs) -> dict:
    return next(r for r in recs if "/RADAR_FRONT/" in r.get("filename", "") and r["prev"])


@pytest.mark.parametrize(
    ("edit", "cause"),
    [
        (lambda r: r.pop("filename"), r"has no 'filename' field, though its calibrated_sensor"),
        (
            lambda r: r.update(filename="maps/abc.png"),
            r"has filename 'maps/abc\.png', not a radar file",
        ),
    ],
)
def test_radar_record_without_radar_filename(clone, edit, cause):
    root = clone()
    bad = {}

    def damage(recs):
        r = _middle_radar(recs)
        bad["token"] = r["token"]
        edit(r)

    _edit_records(root, "sample_data", damage)
    t = NuScenesTables(root, VERSION, use_cache=False)
    with pytest.raises(DataError) as exc:
        _ = t.radar
    msg = str(exc.value)
    assert msg.startswith(
        f"{root / VERSION / 'sample_data.json'}: sample_data record {bad['token']!r}"
    )
    assert "of radar record" in msg
    assert re.search(cause, msg), msg


# ---- ego poses and calibrations: bad values named, non-unit quaternions warned -----------------
def _radar_ego_token(root) -> str:
    sd = json.loads((root / VERSION / "sample_data.json").read_text())
    return _middle_radar(sd)["ego_pose_token"]


def _edit_ego(root, **update) -> str:
    tok_ = _radar_ego_token(root)
    _edit_records(
        root, "ego_pose", lambda rs: next(r for r in rs if r["token"] == tok_).update(update)
    )
    return tok_


@pytest.mark.parametrize(
    ("update", "match"),
    [
        (
            {"rotation": [float("nan"), 0.0, 0.0, 1.0]},
            r"has a non-finite rotation \(rotation \[nan",
        ),
        ({"rotation": [0, 0, 0, 0]}, r"has a zero rotation quaternion \(rotation \[0\.0, 0\.0"),
        (
            {"rotation": [1e-8, 0.0, 0.0, 0.0]},
            r"has a rotation quaternion that has norm 1e-08, not a rotation",
        ),
        ({"rotation": [1e300, 0.0, 0.0, 0.0]}, r"has norm 1e\+300, not a rotation"),
        ({"translation": [1.0, float("inf"), 0.0]}, r"has a non-finite translation .*\[1\.0, inf"),
        ({"translation": ["1", "2", "3"]}, r"field 'translation' is \['1', '2', '3'\], expected 3"),
        ({"translation": [1.0, True, 3.0]}, r"field 'translation' is \[1\.0, True, 3\.0\]"),
        ({"rotation": [1.0, 0.0, None, 0.0]}, r"field 'rotation' is \[1\.0, 0\.0, None, 0\.0\]"),
    ],
)
def test_bad_ego_pose_values_are_named(clone, update, match):
    root = clone()
    tok_ = _edit_ego(root, **update)
    t = NuScenesTables(root, VERSION, use_cache=False)
    with pytest.raises(DataError, match=match) as exc:
        _ = t.radar
    msg = str(exc.value)
    assert msg.startswith(str(root / VERSION / "ego_pose.json")) and repr(tok_) in msg


def test_non_unit_quaternions_are_normalised_with_one_warning(clone, caplog):
    root = clone()
    sd = json.loads((root / VERSION / "sample_data.json").read_text())
    radar_egos = [r["ego_pose_token"] for r in sd if "/RADAR_" in r["filename"]][:5]

    def scale(recs):
        for r in recs:
            if r["token"] in radar_egos:
                r["rotation"] = [3.0 * q for q in r["rotation"]]

    _edit_records(root, "ego_pose", scale)
    cs_tok = {}

    def scale_cs(recs):
        r = recs[_radar_cs(root)]
        cs_tok["t"] = r["token"]
        r["rotation"] = [3.0 * q for q in r["rotation"]]

    _edit_records(root, "calibrated_sensor", scale_cs)
    with caplog.at_level(logging.WARNING, logger="radarslam.nuscenes"):
        t = NuScenesTables(root, VERSION, use_cache=False)
        radar = t.radar
    ego_msgs = [m for m in caplog.messages if "ego_pose.json" in m]
    assert len(ego_msgs) == 1, caplog.messages
    assert "5 ego pose(s) have a rotation quaternion whose norm is not 1" in ego_msgs[0]
    assert "norm 3" in ego_msgs[0] and any(tk in ego_msgs[0] for tk in radar_egos)
    cs_msgs = [m for m in caplog.messages if "calibrated_sensor.json" in m]
    assert len(cs_msgs) == 1 and cs_tok["t"] in cs_msgs[0] and "1 calibrated_sensor" in cs_msgs[0]
    # still normalised: every pose is a rotation
    for i in range(len(radar)):
        rot = t.world_from_ego(i)[:3, :3]
        np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-9)


def _radar_cs(root) -> int:
    sensors = json.loads((root / VERSION / "sensor.json").read_text())
    radar = {r["token"] for r in sensors if r["channel"].startswith("RADAR_")}
    cs = json.loads((root / VERSION / "calibrated_sensor.json").read_text())
    return next(i for i, r in enumerate(cs) if r["sensor_token"] in radar)


def test_calibrated_sensor_non_finite_translation(clone):
    root = clone()
    i = _radar_cs(root)
    _edit_records(root, "calibrated_sensor", lambda rs: rs[i].update(translation=[0.0, 1e999, 0]))
    t = NuScenesTables(root, VERSION, use_cache=False)
    with pytest.raises(DataError, match=r"calibrated_sensor\.json: record '\w+' has a non-finite"):
        _ = t.small


@pytest.mark.parametrize("scale", [1e-8, 0.0, 1e300])
def test_calibrated_sensor_rotation_far_from_unit_is_refused(clone, scale):
    root = clone()
    i = _radar_cs(root)
    tok_ = {}

    def edit(rs):
        tok_["t"] = rs[i]["token"]
        rs[i]["rotation"] = [scale * q for q in rs[i]["rotation"]]

    _edit_records(root, "calibrated_sensor", edit)
    t = NuScenesTables(root, VERSION, use_cache=False)
    with pytest.raises(DataError, match=r"has a degenerate rotation .*: the quaternion ") as exc:
        _ = t.small
    assert str(exc.value).startswith(str(root / VERSION / "calibrated_sensor.json"))
    assert repr(tok_["t"]) in str(exc.value)
