"""NuScenesRadar on the hand-made dataroot: scenes, sweeps, frames, key frames, accumulation."""

from __future__ import annotations

import logging

import numpy as np
import pytest
from mini_dataroot import MOUNTS, PERIOD_US, VERSION, ego_from_sensor

from radarslam.errors import ConfigError, DataError
from radarslam.geometry import invert
from radarslam.nuscenes.filters import RadarPointFilter
from radarslam.nuscenes.pcd import pcd_bytes
from radarslam.nuscenes.reader import NuScenesRadar, stack_in_reference
from radarslam.types import ACCUMULATED_DTYPE, RADAR_CHANNELS, RADAR_DTYPE


# ---- scenes ----------------------------------------------------------------------------------
def test_scenes_and_locations(reader):
    names = [s.name for s in reader.scenes()]
    assert names == ["scene-0004", "scene-0002", "scene-0001", "scene-0003"]  # scene.json order
    s = reader.scene("scene-0003")
    assert (s.location, s.date_captured, s.vehicle, s.nbr_samples) == (
        "singapore-onenorth",
        "2018-08-01",
        "n008",
        6,
    )
    assert reader.locations() == ["boston-seaport", "singapore-onenorth"]
    boston = reader.scenes_for_location("boston-seaport")
    assert [x.name for x in boston] == ["scene-0001", "scene-0002", "scene-0004"]  # date, time
    only = reader.scenes_for_location("boston-seaport", dates=["2018-08-30"])
    assert [x.name for x in only] == ["scene-0004"]
    with pytest.raises(DataError, match=r"unknown scene 'scene-9'.*4 scenes, e\.g\. scene-0004"):
        reader.scene("scene-9")
    with pytest.raises(DataError, match="unknown location 'paris'"):
        reader.scenes_for_location("paris")


# ---- sweeps ----------------------------------------------------------------------------------
@pytest.mark.parametrize("channel", RADAR_CHANNELS)
def test_iter_sweeps_order_frames_and_points(mini, reader, channel):
    sweeps = list(reader.iter_sweeps("scene-0003", channel, filters=RadarPointFilter.none()))
    assert [s.token for s in sweeps] == mini.sweeps[("scene-0003", channel)]
    assert np.all(np.diff([s.timestamp_us for s in sweeps]) > 0)
    for s in sweeps[::7]:
        assert s.channel == channel and s.points.dtype == RADAR_DTYPE
        np.testing.assert_allclose(s.ego_from_sensor, ego_from_sensor(channel), atol=1e-12)
        np.testing.assert_allclose(s.world_from_sensor, mini.world_from_sensor[s.token], atol=1e-9)
        assert s.filename.startswith(("samples/", "sweeps/")) and f"/{channel}/" in s.filename
        # the landmark points are the true landmarks in this sensor's frame
        n = mini.num_landmark_points[s.token]
        lm = mini.landmarks_world[mini.landmark_ids[s.token]]
        p = lm @ invert(s.world_from_sensor)[:3, :3].T + invert(s.world_from_sensor)[:3, 3]
        np.testing.assert_allclose(s.xy[:n], p[:, :2], atol=1e-4)
    keys = list(reader.iter_sweeps("scene-0003", channel, key_frames_only=True))
    assert all(k.is_key_frame for k in keys) and len(keys) == 6
    assert {k.token for k in keys} == {
        mini.keyframes[t][channel] for t in mini.samples["scene-0003"]
    }


def test_filters_apply_per_reader_and_per_call(mini):
    default = NuScenesRadar(mini.dataroot, VERSION, use_cache=False)
    raw = NuScenesRadar(mini.dataroot, VERSION, filters=RadarPointFilter.none(), use_cache=False)
    tok = mini.sweeps[("scene-0003", "RADAR_FRONT")][4]
    a, b = default.load_sweep(tok), raw.load_sweep(tok)
    assert len(a) < len(b)
    assert RadarPointFilter.devkit_default().mask(a.points).all()
    assert len(raw.load_sweep(tok, filters=RadarPointFilter.devkit_default())) == len(a)
    with pytest.raises(DataError, match="'nope' is not a radar record"):
        default.load_sweep("nope")


# ---- frames ----------------------------------------------------------------------------------
def test_iter_frames_groups_and_covers_a_missing_radar(mini, reader):
    frames = list(reader.iter_frames("scene-0001"))
    assert len(frames) == 39  # pinned on the seeded dataset
    t = np.array([f.timestamp_us for f in frames])
    assert np.all(np.diff(t) > 0) and np.diff(t).max() < 1.5 * PERIOD_US  # no hole in the gap
    seen = set()
    start = reader.scene_start_us("scene-0001") - 250_000
    in_gap = 0
    for f in frames:
        tokens = [s.token for s in f.sweeps.values()]
        assert not seen.intersection(tokens)  # each sweep used at most once
        seen.update(tokens)
        assert all(abs(s.timestamp_us - f.timestamp_us) <= PERIOD_US / 2 for s in f.sweeps.values())
        rel = (f.timestamp_us - start) * 1e-6
        if 1.15 < rel < 1.85:  # RADAR_FRONT is missing from 1.05 s to 1.95 s
            in_gap += 1
            assert "RADAR_FRONT" not in f.sweeps and len(f.sweeps) == 4
            assert f.timestamp_us == f.sweeps["RADAR_FRONT_LEFT"].timestamp_us  # next anchor
            np.testing.assert_array_equal(
                f.world_from_ego, f.sweeps["RADAR_FRONT_LEFT"].world_from_ego
            )
        elif "RADAR_FRONT" in f.sweeps:
            assert f.timestamp_us == f.sweeps["RADAR_FRONT"].timestamp_us
            np.testing.assert_array_equal(f.world_from_ego, f.sweeps["RADAR_FRONT"].world_from_ego)
        assert f.scene_name == "scene-0001"
        assert f.is_key_frame == bool(f.sample_token)
    assert in_gap >= 8
    all_tokens = {
        tok for (sc, _), toks in mini.sweeps.items() if sc == "scene-0001" for tok in toks
    }
    assert len(seen) == len(all_tokens) and seen <= all_tokens
    assert sum(len(f.sweeps) for f in frames) == 184  # pinned: 39 frames, 11 without FRONT
    assert reader.frame_count("scene-0001") == len(frames) == 39  # what a progress bar counts
    assert reader.frame_groups("scene-0001")[0] == {
        ch: s.token
        for ch, s in sorted(frames[0].sweeps.items(), key=lambda kv: kv[0] != "RADAR_FRONT")
    }


def test_iter_frames_stride_reads_every_kth_frame(reader):
    full = list(reader.iter_frames("scene-0001"))
    every3 = list(reader.iter_frames("scene-0001", stride=3))
    assert len(every3) == 13  # 39 frames: the 1st, 4th, ... 37th
    for a, b in zip(full[::3], every3, strict=True):
        assert a.timestamp_us == b.timestamp_us
        assert {c: s.token for c, s in a.sweeps.items()} == {
            c: s.token for c, s in b.sweeps.items()
        }
    keys = list(reader.iter_frames("scene-0001", key_frames_only=True))
    keys2 = list(reader.iter_frames("scene-0001", key_frames_only=True, stride=2))
    assert [f.sample_token for f in keys2] == [f.sample_token for f in keys[::2]]
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ConfigError, match="stride must be an integer >= 1"):
            reader.iter_frames("scene-0001", stride=bad)


def test_iter_frames_other_reference_and_tolerance(reader):
    back = list(reader.iter_frames("scene-0003", ref_channel="RADAR_BACK_LEFT"))
    assert all(f.timestamp_us == f.sweeps["RADAR_BACK_LEFT"].timestamp_us for f in back)
    # a 5 ms tolerance leaves only each anchor's own sweep (channels are 11-48 ms apart)
    tight = reader.frame_groups("scene-0003", sync_tolerance_us=5_000)
    assert all(len(g) == 1 for g in tight)
    assert reader.frame_count("scene-0003", ref_channel="RADAR_BACK_LEFT") == len(back)
    assert reader.frame_count("scene-0003", sync_tolerance_us=5_000) == len(tight)
    with pytest.raises(DataError, match="unknown radar channel 'RADAR_TOP'"):
        list(reader.iter_frames("scene-0003", ref_channel="RADAR_TOP"))


def test_key_frames(mini, reader):
    frames = list(reader.iter_frames("scene-0001", key_frames_only=True))
    assert [f.sample_token for f in frames] == mini.samples["scene-0001"]
    for f in frames:
        assert f.is_key_frame and all(s.is_key_frame for s in f.sweeps.values())
        assert {c: s.token for c, s in f.sweeps.items()} == mini.keyframes[f.sample_token]
        anchor = f.sweeps.get("RADAR_FRONT") or f.sweeps["RADAR_FRONT_LEFT"]
        assert f.timestamp_us == anchor.timestamp_us
    assert [len(f.sweeps) for f in frames] == [5, 5, 4, 4, 5, 5]


# ---- accumulation ----------------------------------------------------------------------------
def _sweep_token(mini, scene, sample, channel, k):
    toks = mini.sweeps[(scene, channel)]
    return toks[toks.index(mini.keyframes[sample][channel]) - k]


def test_accumulate_static_landmarks_and_rotated_velocities(mini, reader):
    scene = "scene-0003"
    sample = mini.samples[scene][3]
    acc = reader.accumulate(sample, nsweeps=7)
    assert acc.points.dtype == ACCUMULATED_DTYPE and acc.ref_channel == "RADAR_FRONT"
    assert sum(acc.num_points_per_sweep.values()) == len(acc) == 1329  # pinned
    assert set(acc.num_points_per_sweep) == {(c, k) for c in RADAR_CHANNELS for k in range(7)}
    ref_tok = mini.keyframes[sample]["RADAR_FRONT"]
    np.testing.assert_allclose(acc.world_from_ref, mini.world_from_sensor[ref_tok], atol=1e-9)
    ref_from_world = invert(acc.world_from_ref)
    lm_ref = mini.landmarks_world @ ref_from_world[:3, :3].T + ref_from_world[:3, 3]

    p = acc.points
    static = (p["vx_comp"] == 0) & (p["vy_comp"] == 0)  # landmark points (clutter has v_comp)
    assert static.sum() > 800
    xyz = np.column_stack([p["x"], p["y"], p["z"]])[static]
    d = np.linalg.norm(xyz[:, None, :] - lm_ref[None, :, :], axis=2)
    nearest, dist = d.argmin(axis=1), d.min(axis=1)
    assert dist.max() < 1e-4  # every static point lands on its landmark
    chans, sweeps = p["channel"][static], p["sweep"][static]
    multi = [
        lid
        for lid in np.unique(nearest)
        if len(set(chans[nearest == lid])) >= 2 and len(set(sweeps[nearest == lid])) >= 2
    ]
    assert len(multi) >= 5  # seen by several radars and sweeps, all on one point

    # velocities are rotated into the reference frame with the points
    rot_err, raw_err = [], []
    for c, ch in enumerate(RADAR_CHANNELS):
        for k in range(7):
            sel = static & (p["channel"] == c) & (p["sweep"] == k)
            if not sel.any():
                continue
            v_s = mini.sensor_velocity_world[_sweep_token(mini, scene, sample, ch, k)]
            want = -(ref_from_world[:3, :3] @ v_s)[:2]
            got = np.column_stack([p["vx"][sel], p["vy"][sel]])
            rot_err.append(np.abs(got - want).max())
            w_from_s = mini.world_from_sensor[_sweep_token(mini, scene, sample, ch, k)]
            unrotated = -(w_from_s[:3, :3].T @ v_s)[:2]  # what the devkit leaves in place
            raw_err.append(np.abs(unrotated - want).max())
    assert max(rot_err) < 1e-4
    assert max(raw_err) > 5.0  # the back radars face backwards: not rotating would be wrong
    # sweep 0 is the key frame; time lags grow with the sweep index
    lag = [p["time_lag_s"][(p["channel"] == 0) & (p["sweep"] == k)] for k in range(7)]
    assert lag[0].max() == 0.0 and all(np.all(lag[k] > lag[k - 1].max()) for k in range(1, 7))
    assert abs(lag[6][0] - 6 * PERIOD_US * 1e-6) < 0.004


def test_accumulate_matches_devkit_multisweep(mini, reader):
    pytest.importorskip("nuscenes")
    from nuscenes.nuscenes import NuScenes
    from nuscenes.utils.data_classes import RadarPointCloud

    nusc = NuScenes(VERSION, str(mini.dataroot), verbose=False)
    sample = nusc.get("sample", mini.samples["scene-0003"][1])
    for c, ch in enumerate(RADAR_CHANNELS):
        pc, times = RadarPointCloud.from_file_multisweep(nusc, sample, ch, "RADAR_FRONT", nsweeps=5)
        acc = reader.accumulate(sample["token"], nsweeps=5, channels=[ch])
        p = acc.points
        assert (p["channel"] == c).all() and len(p) == pc.nbr_points()
        for i, name in enumerate(("x", "y", "z")):
            np.testing.assert_allclose(p[name], pc.points[i], atol=1e-9)
        np.testing.assert_allclose(p["time_lag_s"], times[0], atol=1e-6)
        np.testing.assert_array_equal(p["rcs"], pc.points[5].astype(np.float32))


def test_accumulate_options(mini, reader):
    scene = "scene-0003"
    first = mini.samples[scene][0]  # 0.25 s into the scene: fewer than 7 sweeps exist
    acc = reader.accumulate(first, nsweeps=7, channels=["RADAR_FRONT"])
    assert sorted(k for _, k in acc.num_points_per_sweep) == [0, 1, 2, 3]

    sample = mini.samples[scene][2]
    near = reader.accumulate(sample, min_distance_m=0.0)
    far = reader.accumulate(sample, min_distance_m=1.0)
    close = 0
    for ch in RADAR_CHANNELS:
        for k in range(7):
            pts = reader.load_sweep(_sweep_token(mini, scene, sample, ch, k)).points
            close += int(((np.abs(pts["x"]) < 1) & (np.abs(pts["y"]) < 1)).sum())
    assert len(near) - len(far) == close == 2  # the devkit's remove_close square, after filters
    only_static = reader.accumulate(sample, point_mask=lambda s: s.points["dyn_prop"] != 3)
    assert len(only_static) < len(far) and not (only_static.points["dyn_prop"] == 3).any()
    with pytest.raises(ValueError, match="point_mask must return a bool array"):
        reader.accumulate(sample, point_mask=lambda s: np.ones(3))

    ego = reader.accumulate(sample, ref_channel=None, nsweeps=3)
    assert ego.ref_channel is None
    key_front = reader.load_sweep(mini.keyframes[sample]["RADAR_FRONT"])
    np.testing.assert_allclose(ego.world_from_ref, key_front.world_from_ego, atol=1e-12)
    # same points as the sensor-frame cloud, moved by the fixed ego_from_sensor
    sensor = reader.accumulate(sample, nsweeps=3)
    e_from_s = ego_from_sensor("RADAR_FRONT")
    xyz = np.column_stack([sensor.points[n] for n in ("x", "y", "z")]) @ e_from_s[:3, :3].T
    np.testing.assert_allclose(np.column_stack([ego.points["x"], ego.points["y"]]),
                               (xyz + e_from_s[:3, 3])[:, :2], atol=1e-9)  # fmt: skip
    assert MOUNTS["RADAR_FRONT"][0] > 3.0


def test_accumulate_errors(mini, reader):
    with pytest.raises(DataError, match="sample token 'x' is not in"):
        reader.accumulate("x")
    gap_sample = mini.samples["scene-0001"][2]  # RADAR_FRONT missing at 1.25 s
    with pytest.raises(DataError, match="has no RADAR_FRONT key-frame sweep"):
        reader.accumulate(gap_sample)
    acc = reader.accumulate(gap_sample, ref_channel="RADAR_FRONT_LEFT")
    assert len(acc) > 0 and 0 not in set(acc.points["channel"].tolist())  # FRONT has no key frame


# ---- documented skips and bad files ------------------------------------------------------------
def test_empty_sweeps_and_nan_points_are_counted(mini, reader, caplog):
    with caplog.at_level(logging.WARNING, logger="radarslam.nuscenes"):
        frames = list(reader.iter_frames("scene-0002"))
        list(reader.iter_sweeps("scene-0002", "RADAR_BACK_LEFT"))  # again: counted, not re-warned
    assert reader.skip_counts.empty_sweeps == 2 and reader.skip_counts.nan_points == 3
    assert reader.skip_counts.per_scene == {
        "scene-0002": {"nan_points": 3, "empty_sweeps": 2, "far_points": 0}
    }
    assert (
        "scene scene-0002: 2 empty sweep(s)" in caplog.text and "3 point(s) with NaN" in caplog.text
    )
    assert caplog.text.count("scene scene-0002") == 1  # once per scene
    empties = [s for f in frames for s in f.sweeps.values() if s.token in mini.empty_tokens]
    assert len(empties) == 2 and all(len(s) == 0 for s in empties)
    for tok in mini.nan_tokens:
        s = reader.load_sweep(tok, filters=RadarPointFilter.none())
        assert all(np.isfinite(s.points[f]).all() for f in ("x", "vx_comp"))


def test_scene_with_only_empty_sweeps_is_an_error(mini, clone):
    root = clone(copy_files=True)
    reader = NuScenesRadar(root, VERSION, use_cache=False)
    empty = pcd_bytes(np.zeros(0, dtype=RADAR_DTYPE))
    for ch in RADAR_CHANNELS:
        for t in mini.sweeps.get(("scene-0003", ch), []):
            (root / reader.load_sweep(t).filename).write_bytes(empty)
    reader = NuScenesRadar(root, VERSION, use_cache=False)
    # one radar at a time: empty sweeps are yielded, as documented
    assert all(len(s) == 0 for s in reader.iter_sweeps("scene-0003", "RADAR_FRONT"))
    frames = []
    with pytest.raises(
        DataError, match=r"scene 'scene-0003': all \d+ radar sweeps are empty"
    ) as exc:
        for f in reader.iter_frames("scene-0003"):
            frames.append(f)
    assert str(root) in str(exc.value) and ".pcd" in str(exc.value)
    assert len(frames) > 0  # raised at the end of the scene, after its (empty) frames
    # a scene with some empty sweeps (scene-0002 has 2) is not an error
    assert len(list(reader.iter_frames("scene-0002"))) > 0


@pytest.mark.parametrize(
    ("damage", "match"),
    [
        (lambda p: p.unlink(), "radar file is missing"),
        (lambda p: p.write_bytes(p.read_bytes()[:400]), "truncated: header says"),
        (
            lambda p: p.write_bytes(p.read_bytes().replace(b"DATA binary", b"DATA ascii")),
            "DATA ascii",
        ),
        (
            lambda p: p.write_bytes(p.read_bytes().replace(b"FIELDS x", b"FIELDS q")),
            "unexpected field",
        ),
    ],
)
def test_bad_pcd_files(mini, clone, damage, match):
    root = clone(copy_files=True)
    reader = NuScenesRadar(root, VERSION, use_cache=False)
    tok = mini.sweeps[("scene-0003", "RADAR_FRONT")][5]
    path = root / reader.load_sweep(tok).filename
    damage(path)
    with pytest.raises(DataError, match=match) as exc:
        list(reader.iter_sweeps("scene-0003", "RADAR_FRONT"))
    assert str(exc.value).startswith(str(path))


def test_bad_dataroot(tmp_path):
    with pytest.raises(DataError, match="dataroot does not exist"):
        NuScenesRadar(tmp_path / "missing")
    (tmp_path / "v1.0-mini").mkdir()
    with pytest.raises(DataError, match=r"scene\.json: table file is missing"):
        NuScenesRadar(tmp_path)


def test_stack_in_reference_is_each_sweep_transformed_then_concatenated():
    from radarslam.geometry import make_transform

    rng = np.random.default_rng(3)
    parts, expected = [], []
    for k, n in enumerate([5, 0, 12, 1]):  # an empty sweep contributes nothing
        pts = np.zeros(n, dtype=RADAR_DTYPE)
        for name in ("x", "y", "z", "rcs", "vx", "vy", "vx_comp", "vy_comp"):
            pts[name] = rng.normal(0, 20, n)
        pts["dyn_prop"] = rng.integers(0, 7, n)
        q = rng.normal(size=4)
        pose = make_transform(rng.normal(0, 5, 3), q / np.linalg.norm(q))
        parts.append((pts, pose, k % 5, k, 0.1 * k))
        one = np.zeros(n, dtype=ACCUMULATED_DTYPE)
        xyz = np.column_stack([pts["x"], pts["y"], pts["z"]]) @ pose[:3, :3].T + pose[:3, 3]
        one["x"], one["y"], one["z"] = xyz.T
        for a, b in (("vx", "vy"), ("vx_comp", "vy_comp")):
            v = np.column_stack([pts[a], pts[b], np.zeros(n)]) @ pose[:3, :3].T
            one[a], one[b] = v[:, 0], v[:, 1]
        one["rcs"], one["dyn_prop"] = pts["rcs"], pts["dyn_prop"]
        one["channel"], one["sweep"], one["time_lag_s"] = k % 5, k, 0.1 * k
        expected.append(one)
    got = stack_in_reference(parts)
    want = np.concatenate(expected)
    assert got.dtype == ACCUMULATED_DTYPE and len(got) == 18
    for name in ACCUMULATED_DTYPE.names:
        np.testing.assert_allclose(got[name], want[name], rtol=1e-6, atol=1e-9, err_msg=name)
    assert len(stack_in_reference([])) == 0


# ---- argument checks -----------------------------------------------------------------------------
def test_scene_info_of_another_dataset_is_a_data_error(mini, reader, clone):
    import dataclasses

    info = reader.scene("scene-0001")
    assert reader.scene(info) is info and reader.samples(info) == mini.samples["scene-0001"]
    # another dataroot holding a scene of the same name under another token
    root = clone()
    for path in (root / VERSION).glob("*.json"):
        path.write_text(path.read_text().replace(info.token, "0" * 32))
    other = NuScenesRadar(root, VERSION, use_cache=False).scene("scene-0001")
    assert other.name == info.name and other.token != info.token
    match = (
        f"scene 'scene-0001' \\(token '{'0' * 32}'\\) is not a scene of .*{VERSION} \\(its "
        f"'scene-0001' has token '{info.token}'\\)"
    )
    for call in (
        lambda s: reader.samples(s),
        lambda s: reader.iter_frames(s),
        lambda s: reader.frame_groups(s),
        lambda s: reader.frame_count(s),
        lambda s: list(reader.iter_sweeps(s, "RADAR_FRONT")),
    ):
        with pytest.raises(DataError, match=match):
            call(other)
    fake = dataclasses.replace(info, name="scene-fake")
    with pytest.raises(DataError, match=r"scene 'scene-fake' .* \(no such name\)"):
        reader.iter_frames(fake)
    with pytest.raises(DataError, match="scene must be a scene name or a SceneInfo, got int 3"):
        reader.samples(3)


@pytest.mark.parametrize("tol", [-5, 0, float("nan"), float("inf"), "38000", True])
def test_bad_sync_tolerance_is_a_config_error(reader, tol):
    with pytest.raises(ConfigError, match=f"sync_tolerance_us must be .*got {tol!r}"):
        reader.iter_frames("scene-0001", sync_tolerance_us=tol)  # at the call, not on next()
    with pytest.raises(ConfigError, match="sync_tolerance_us"):
        reader.frame_groups("scene-0001", sync_tolerance_us=tol)
    with pytest.raises(ConfigError, match="sync_tolerance_us"):
        reader.frame_count("scene-0001", sync_tolerance_us=tol)


def test_bad_filters_are_a_config_error(mini, reader):
    match = "filters must be a RadarPointFilter or None, got str 'none'"
    with pytest.raises(ConfigError, match=match):
        reader.iter_frames("scene-0001", filters="none")
    with pytest.raises(ConfigError, match=match):
        reader.iter_sweeps("scene-0001", "RADAR_FRONT", filters="none")  # at the call
    sample = mini.samples["scene-0003"][2]
    with pytest.raises(ConfigError, match=match):
        reader.accumulate(sample, filters="none")
    with pytest.raises(ConfigError, match=match):
        reader.load_sweep(mini.keyframes[sample]["RADAR_FRONT"], filters="none")


def test_accumulate_arguments(mini, reader):
    sample = mini.samples["scene-0003"][2]
    one = reader.accumulate(sample, channels="RADAR_FRONT")  # a bare name is one channel
    assert (
        one.num_points_per_sweep
        == reader.accumulate(sample, channels=["RADAR_FRONT"]).num_points_per_sweep
    )
    assert {c for c, _ in one.num_points_per_sweep} == {"RADAR_FRONT"}
    assert len(reader.accumulate(sample, nsweeps=np.int64(2))) > 0
    for n in (0, 2.5, "3", True):
        with pytest.raises(ConfigError, match=f"nsweeps must be an integer >= 1, got {n!r}"):
            reader.accumulate(sample, nsweeps=n)
    for d in (-1, float("nan"), "1"):
        with pytest.raises(
            ConfigError, match=f"min_distance_m must be a finite number >= 0, got {d!r}"
        ):
            reader.accumulate(sample, min_distance_m=d)
    with pytest.raises(ConfigError, match="channels must be a radar channel name or a list"):
        reader.accumulate(sample, channels=5)


def test_points_beyond_the_physical_range_are_dropped_and_reported_once(mini, clone, caplog):
    from radarslam.nuscenes.pcd import read_pcd
    from radarslam.nuscenes.reader import MAX_POINT_COORDINATE_M

    root = clone(copy_files=True)
    reader = NuScenesRadar(root, VERSION, use_cache=False)
    tokens = reader.sweep_tokens("scene-0004", "RADAR_FRONT")[3:5]
    dropped = 0
    for tok, far in zip(tokens, (1e30, 1e10), strict=True):
        path = root / reader.load_sweep(tok).filename
        pts = read_pcd(path)
        pts["x"][::3] = far
        dropped += len(pts[::3])
        path.write_bytes(pcd_bytes(pts))
    reader = NuScenesRadar(root, VERSION, use_cache=False, filters=RadarPointFilter.none())
    with caplog.at_level(logging.WARNING, logger="radarslam.nuscenes"):
        frames = list(reader.iter_frames("scene-0004"))
        list(reader.iter_sweeps("scene-0004", "RADAR_FRONT"))  # again: not re-warned
    assert reader.skip_counts.far_points == dropped
    assert reader.skip_counts.per_scene["scene-0004"]["far_points"] == dropped
    assert caplog.text.count(f"{dropped} point(s) farther than 1000 m") == 1
    for f in frames:
        for s in f.sweeps.values():
            assert np.abs(s.points["x"]).max(initial=0) <= MAX_POINT_COORDINATE_M


def test_sweep_files_name_each_sweep_as_loading_it_does(mini, reader):
    files = reader.sweep_files("scene-0004", "RADAR_FRONT_LEFT")
    sweeps = list(reader.iter_sweeps("scene-0004", "RADAR_FRONT_LEFT"))
    assert files == [(s.filename, s.timestamp_us) for s in sweeps]
    assert all((mini.dataroot / name).is_file() for name, _ in files)
    assert [t for _, t in files] == sorted(t for _, t in files)
