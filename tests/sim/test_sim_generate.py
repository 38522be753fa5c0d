"""The synthetic generator: nuScenes layout, devkit compatibility, determinism, scenario knobs."""

from __future__ import annotations

import hashlib
import json
import re
from pathlib import Path

import numpy as np
import pytest

from radarslam.errors import ConfigError, DataError
from radarslam.nuscenes.pcd import read_pcd
from radarslam.sim.ego import read_tum
from radarslam.sim.generate import CHANNELS, TABLES, is_complete, simulate
from radarslam.types import RADAR_DTYPE

VERSION = "v1.0-mini"
SHORT = ["schedule.scenes_per_log=1", "schedule.scene_duration_s=3.0", "traffic.warmup_s=5.0"]


def _table(root: Path, name: str, version: str = VERSION) -> list[dict]:
    return json.loads((root / version / f"{name}.json").read_text())


def _digest(root: Path) -> str:
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if p.is_file() and p.name != "summary.json":  # timing and paths differ
            h.update(str(p.relative_to(root)).encode())
            h.update(p.read_bytes())
    return h.hexdigest()


def test_deterministic_for_a_seed(tmp_path):
    a = simulate("tiny", tmp_path / "a", progress=False, overrides=SHORT)
    b = simulate("tiny", tmp_path / "b", progress=False, overrides=SHORT)
    c = simulate("tiny", tmp_path / "c", seed=99, progress=False, overrides=SHORT)
    assert a.n_sweeps == b.n_sweeps > 150
    assert _digest(tmp_path / "a") == _digest(tmp_path / "b")
    assert _digest(tmp_path / "a") != _digest(tmp_path / "c")
    tok_a = {r["token"] for r in _table(tmp_path / "a", "sample_data")}
    tok_c = {r["token"] for r in _table(tmp_path / "c", "sample_data")}
    assert not tok_a & tok_c
    assert all(re.fullmatch(r"[0-9a-f]{32}", t) for t in tok_a)
    assert c.seed == 99


def test_refuses_to_overwrite_and_completion_marker(tmp_path):
    simulate("tiny", tmp_path, progress=False, overrides=SHORT)
    assert is_complete(tmp_path, VERSION)
    with pytest.raises(ConfigError, match="--overwrite"):
        simulate("tiny", tmp_path, progress=False, overrides=SHORT)
    (tmp_path / VERSION / "scene.json").unlink()  # as if interrupted before the tables
    assert not is_complete(tmp_path, VERSION)
    simulate("tiny", tmp_path, progress=False, overrides=SHORT, overwrite=True)
    assert is_complete(tmp_path, VERSION)


def test_layout_and_tables(tiny_dataroot):
    root = tiny_dataroot
    for t in TABLES:
        assert (root / VERSION / f"{t}.json").is_file(), t
    scenes = _table(root, "scene")
    samples = _table(root, "sample")
    sds = _table(root, "sample_data")
    poses = {r["token"]: r for r in _table(root, "ego_pose")}
    logs = _table(root, "log")
    assert len(scenes) == 2 and len(logs) == 1
    assert re.fullmatch(r"\d{4}-\d{2}-\d{2}", logs[0]["date_captured"])
    assert logs[0]["location"] == "synth-seaport"
    assert sum(s["nbr_samples"] for s in scenes) == len(samples)
    for s in scenes:
        assert 16 <= s["nbr_samples"] <= 20  # ~9 s at 2 Hz
    by_sample = {s["token"]: s for s in samples}
    key_channels: dict[str, set] = {s["token"]: set() for s in samples}
    pat = re.compile(r"(samples|sweeps)/(RADAR_\w+)/(.+)__(RADAR_\w+)__(\d+)\.pcd")
    sd_by_tok = {r["token"]: r for r in sds}
    for r in sds:
        m = pat.fullmatch(r["filename"])
        assert m, r["filename"]
        assert m.group(2) == m.group(4)
        assert m.group(3) == logs[0]["logfile"]
        assert int(m.group(5)) == r["timestamp"]
        assert (m.group(1) == "samples") == r["is_key_frame"]
        assert r["fileformat"] == "pcd" and r["width"] == 0 and r["height"] == 0
        assert poses[r["ego_pose_token"]]["timestamp"] == r["timestamp"]  # GT at every sweep
        if r["is_key_frame"]:
            key_channels[r["sample_token"]].add(m.group(2))
            # The key frame is the sweep of that radar nearest the sample time (13 Hz).
            assert abs(r["timestamp"] - by_sample[r["sample_token"]]["timestamp"]) < 40_000
        else:  # a sweep belongs to the sample nearest in time
            assert abs(r["timestamp"] - by_sample[r["sample_token"]]["timestamp"]) <= 260_000
        if r["next"]:
            nxt = sd_by_tok[r["next"]]
            assert nxt["prev"] == r["token"]
            assert nxt["filename"].split("/")[1] == m.group(2)
            assert 60_000 < nxt["timestamp"] - r["timestamp"] < 95_000  # ~13 Hz with jitter
    assert all(v == set(CHANNELS) for v in key_channels.values())
    # One chain per radar per scene: 2 scenes x 5 radars heads, each a key frame (as nuScenes).
    heads = [r for r in sds if not r["prev"]]
    assert len(heads) == 10 and all(r["is_key_frame"] for r in heads)
    # Real files carry trailing zero padding after the records.
    for r in sds[:50]:
        data = (root / r["filename"]).read_bytes()
        n = len(read_pcd(root / r["filename"]))
        header = data[: data.index(b"DATA binary\n") + len(b"DATA binary\n")]
        pad = data[len(header) + 43 * n :]
        assert 200 <= len(pad) <= 2000 and not pad.strip(b"\x00")
    sensors = _table(root, "sensor")
    assert sorted(s["channel"] for s in sensors) == sorted(CHANNELS)
    cal = _table(root, "calibrated_sensor")
    front = next(
        c
        for c in cal
        if sensors[[s["token"] for s in sensors].index(c["sensor_token"])]["channel"]
        == "RADAR_FRONT"
    )
    assert front["translation"] == pytest.approx([3.412, 0.0, 0.5])
    assert front["camera_intrinsic"] == []
    assert (root / _table(root, "map")[0]["filename"]).is_file()
    assert (root / "synthetic" / "world.npz").is_file()


def test_devkit_loads_and_reads_identical_points(tiny_dataroot):
    pytest.importorskip("nuscenes")
    from nuscenes.nuscenes import NuScenes
    from nuscenes.utils.data_classes import RadarPointCloud

    nusc = NuScenes(VERSION, str(tiny_dataroot), verbose=False)
    assert len(nusc.scene) == 2
    sample = nusc.get("sample", nusc.scene[1]["first_sample_token"])
    assert set(sample["data"]) == set(CHANNELS)
    tokens = [sample["data"][ch] for ch in CHANNELS]
    sd = nusc.get("sample_data", tokens[0])
    while sd["next"] and len(tokens) < 30:
        sd = nusc.get("sample_data", sd["next"])
        tokens.append(sd["token"])
    RadarPointCloud.disable_filters()
    try:
        for tok in tokens:
            path = nusc.get_sample_data_path(tok)
            pc = RadarPointCloud.from_file(path)
            ours = read_pcd(path)
            assert pc.points.shape == (18, len(ours))
            ref = np.stack([ours[f].astype(np.float64) for f in RADAR_DTYPE.names])
            np.testing.assert_array_equal(pc.points, ref)
    finally:
        RadarPointCloud.default_filters()
    # With the default filters about half of the points survive.
    kept = [RadarPointCloud.from_file(nusc.get_sample_data_path(t)).nbr_points() for t in tokens]
    total = [len(read_pcd(nusc.get_sample_data_path(t))) for t in tokens]
    assert 0.35 < sum(kept) / sum(total) < 0.7


def test_scenario_knobs_missing_radar_and_empty_window(sim_dataroot):
    root = sim_dataroot(
        [
            *SHORT[:1],
            "scenario.missing_radar=[{channel: RADAR_BACK_LEFT, start_s: 0.0, end_s: 7.5}]",
            "scenario.empty_windows=[{start_s: 7.5, end_s: 9.0}]",
        ]
    )
    sds = _table(root, "sample_data")
    samples = sorted(_table(root, "sample"), key=lambda s: s["timestamp"])
    t0 = samples[0]["timestamp"]
    back = [r for r in sds if "/RADAR_BACK_LEFT/" in r["filename"]]
    front = [r for r in sds if "/RADAR_FRONT/" in r["filename"]]
    assert back and len(back) < 0.56 * len(front)
    key_back = {r["sample_token"] for r in back if r["is_key_frame"]}
    assert any(s["token"] not in key_back for s in samples)  # samples lacking that radar
    n_empty = 0
    for r in front:
        n = len(read_pcd(root / r["filename"]))
        n_empty += n == 0
    assert 17 <= n_empty <= 21  # ~19.5 sweeps at 13 Hz in the 1.5 s window
    assert samples[-1]["timestamp"] - t0 > 7e6


def test_bad_inputs_are_one_line_errors(tmp_path):
    with pytest.raises(ConfigError, match="unknown key"):
        simulate("tiny", tmp_path / "x", progress=False, overrides=["radar.nope=1"])
    with pytest.raises(ConfigError, match="unknown channel"):
        simulate(
            "tiny",
            tmp_path / "y",
            progress=False,
            overrides=["scenario.missing_radar=[{channel: RADAR_TOP, start_s: 0, end_s: 1}]"],
        )
    with pytest.raises(ConfigError, match="preset"):
        simulate("nonexistent", tmp_path / "z", progress=False)
    bad = tmp_path / "bad.tum"
    bad.write_text("0 1 2 3\n")
    with pytest.raises(DataError, match="expected 8 values"):
        simulate("tiny", tmp_path / "w", progress=False, trajectory_tum=bad)
    assert not (tmp_path / "w").exists()  # validated before anything is written


def test_bad_tum_files_name_the_file(tmp_path):
    binary = tmp_path / "drive.tum"
    binary.write_bytes(b"\x89PNG\r\n\x1a\n\xff\xfe\x00" * 20)
    with pytest.raises(DataError, match=r"drive\.tum: not a UTF-8 text file \(a TUM"):
        read_tum(binary)
    dup = tmp_path / "dup.tum"
    dup.write_text("".join(f"{t} {t} 0 0 0 0 0 1\n" for t in (0.0, 0.1, 0.1, 0.2, 0.3)))
    with pytest.raises(
        DataError, match=r"dup\.tum:3: timestamp 0\.1 is not later than the previous"
    ):
        read_tum(dup)


def test_a_jump_in_a_tum_trajectory_is_refused(tmp_path):
    """A pose far from the previous one (a corrupt line, other units) would make the city
    follow it: a street of one point per metre, the process killed for memory."""
    rows = [f"{t:.1f} {10 * t} 0 0 0 0 0 1" for t in np.arange(0.0, 6.0, 0.5)]
    rows[4] = "2.0 1e9 0 0 0 0 0 1"
    jump = tmp_path / "jump.tum"
    jump.write_text("# t x y z qx qy qz qw\n" + "\n".join(rows) + "\n")
    with pytest.raises(
        DataError, match=r"jump\.tum:6: pose is 1e\+09 m from the previous one 0\.5 s earlier"
    ):
        read_tum(jump)
    with pytest.raises(DataError, match="a vehicle drives at most 100 m/s"):
        simulate("tiny", tmp_path / "out", progress=False, trajectory_tum=jump)
    assert not (tmp_path / "out").exists()


def test_tum_trajectory_is_followed_exactly(tmp_path):
    t = np.arange(0.0, 8.01, 0.1)
    radius, omega = 40.0, 0.15
    cx, cy = 400.0, 400.0
    yaw = omega * t + np.pi / 2
    rows = [
        f"{1e9 + ti:.3f} {cx + radius * np.cos(omega * ti):.6f} "
        f"{cy + radius * np.sin(omega * ti):.6f} "
        f"0 0 0 {np.sin(a / 2):.9f} {np.cos(a / 2):.9f}"
        for ti, a in zip(t, yaw, strict=True)
    ]
    tum = tmp_path / "circle.tum"
    tum.write_text("# t x y z qx qy qz qw\n" + "\n".join(rows) + "\n")
    s = simulate(
        "tiny",
        tmp_path / "out",
        progress=False,
        trajectory_tum=tum,
        overrides=["traffic.warmup_s=5.0"],
    )
    assert s.n_scenes >= 1
    poses = _table(tmp_path / "out", "ego_pose")
    xy = np.array([p["translation"][:2] for p in poses])
    r = np.hypot(xy[:, 0] - cx, xy[:, 1] - cy)
    np.testing.assert_allclose(r, radius, atol=0.02)
    q = np.array([p["rotation"] for p in poses])
    yaw_p = 2 * np.arctan2(q[:, 3], q[:, 0])
    tangent = np.arctan2(xy[:, 1] - cy, xy[:, 0] - cx) + np.pi / 2
    assert np.abs((yaw_p - tangent + np.pi) % (2 * np.pi) - np.pi).max() < 2e-3


def _moving_fraction(root: Path, channel: str = "RADAR_FRONT") -> float:
    sds = [r for r in _table(root, "sample_data") if f"/{channel}/" in r["filename"]]
    pts = np.concatenate([read_pcd(root / r["filename"]) for r in sds])
    keep = (pts["invalid_state"] == 0) & (pts["ambig_state"] == 3) & (pts["dyn_prop"] <= 6)
    xy = np.column_stack([pts["x"], pts["y"]]).astype(np.float64)
    u = xy / np.linalg.norm(xy, axis=1, keepdims=True)
    vr = np.abs(u[:, 0] * pts["vx_comp"] + u[:, 1] * pts["vy_comp"])
    return float(np.mean(vr[keep] > 0.5))


def test_dense_traffic_knob_raises_the_moving_fraction(tiny_dataroot, sim_dataroot):
    dense = sim_dataroot([SHORT[0], "traffic.route_density_per_km=60", "traffic.signals=false"])
    base = _moving_fraction(tiny_dataroot)
    busy = _moving_fraction(dense)
    assert base < 0.12 and busy > 2 * base and busy > 0.12


def test_logs_on_different_days_revisit_streets_in_both_directions(sim_dataroot):
    root = sim_dataroot(
        ["schedule.n_logs=2", "schedule.n_days=5", "schedule.scenes_per_log=1",
         "traffic.warmup_s=10.0"]
    )  # fmt: skip
    logs = _table(root, "log")
    assert len({lg["date_captured"] for lg in logs}) == 2
    poses = {p["token"]: p for p in _table(root, "ego_pose")}
    tracks: dict[str, list] = {lg["logfile"]: [] for lg in logs}
    for r in _table(root, "sample_data"):
        p = poses[r["ego_pose_token"]]
        q = p["rotation"]
        yaw = 2 * np.arctan2(q[3], q[0])
        tracks[r["filename"].split("/")[2].split("__")[0]].append((*p["translation"][:2], yaw))
    a, b = (np.array(t) for t in tracks.values())
    d = np.linalg.norm(a[:, None, :2] - b[None, :, :2], axis=-1)
    close = np.argwhere(d < 4.0)
    assert len(close) > 0, "the two logs never drive the same street"
    dyaw = np.abs((a[close[:, 0], 2] - b[close[:, 1], 2] + np.pi) % (2 * np.pi) - np.pi)
    assert np.mean(dyaw > 2.6) > 0.8  # the second log drives it the other way round
