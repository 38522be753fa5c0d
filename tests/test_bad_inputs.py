"""Every bad input a user or a hostile file can give: one ``error:`` line, exit status 2.

One row per bad input: its name, how it is made from a fresh copy of the tiny synthetic dataroot
(or a file beside it), the command line, and a piece of the expected error line. Each row checks
that ``radarslam`` exits with status 2, prints exactly one line starting with ``error:`` on
stderr and no traceback, and leaves the input files as they were. A new reader, writer or
setting joins the table with its own rows.

The CLI runs in this process (``radarslam.cli.main`` with ``sys.argv`` set), on one copy of the
dataroot per row: the tables are copied, the radar files hard-linked (a damage that edits one
replaces it instead of writing through the link).
"""

from __future__ import annotations

import hashlib
import json
import os
import shlex
import shutil
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

VERSION = "v1.0-mini"
Damage = Callable[[Path, Path], None]  # (dataroot copy, scratch folder) -> None


# ---- ways to damage a dataroot copy --------------------------------------------------------------
def _edit_table(name: str, edit: Callable[[list[dict]], None]) -> Damage:
    def damage(root: Path, tmp: Path) -> None:
        path = root / VERSION / f"{name}.json"
        records = json.loads(path.read_text())
        edit(records)
        path.write_text(json.dumps(records))  # NaN / Infinity written as JSON extensions

    return damage


def _radar_ego_poses(edit: Callable[[dict], None]) -> Damage:
    """Edit the ego poses of the radar sample_data (the ones the radar path reads)."""

    def damage(root: Path, tmp: Path) -> None:
        sd = json.loads((root / VERSION / "sample_data.json").read_text())
        tokens = {r["ego_pose_token"] for r in sd if "RADAR_" in r["filename"]}
        _edit_table("ego_pose", lambda rs: [edit(r) for r in rs if r["token"] in tokens])(root, tmp)

    return damage


def _radar_calibrations(edit: Callable[[dict], None]) -> Damage:
    def damage(root: Path, tmp: Path) -> None:
        sensors = json.loads((root / VERSION / "sensor.json").read_text())
        radar = {r["token"] for r in sensors if r["channel"].startswith("RADAR_")}
        _edit_table(
            "calibrated_sensor", lambda rs: [edit(r) for r in rs if r["sensor_token"] in radar]
        )(root, tmp)

    return damage


def _scale_rotation(factor: float) -> Callable[[dict], None]:
    def edit(rec: dict) -> None:
        rec["rotation"] = [factor * q for q in rec["rotation"]]

    return edit


def _first_pcd(root: Path) -> Path:
    return sorted((root / "sweeps" / "RADAR_FRONT").glob("*.pcd"))[0]


def _replace(path: Path, data: bytes) -> None:
    path.unlink()  # a hard link to the shared dataroot: never write through it
    path.write_bytes(data)


def _truncate_pcd_header(root: Path, tmp: Path) -> None:
    path = _first_pcd(root)
    _replace(path, path.read_bytes()[:100])


def _truncate_pcd_points(root: Path, tmp: Path) -> None:
    path = _first_pcd(root)
    data = path.read_bytes()
    _replace(path, data[: data.index(b"DATA binary\n") + 12 + 10])  # 10 bytes of points


def _remove(relative: str) -> Damage:
    def damage(root: Path, tmp: Path) -> None:
        (root / relative).unlink()

    return damage


def _write(relative: str, text: str) -> Damage:
    """A file in the scratch folder (a config, a file where a folder should be)."""

    def damage(root: Path, tmp: Path) -> None:
        (tmp / relative).write_text(text)

    return damage


def _no_samples_in_second_scene(root: Path, tmp: Path) -> None:
    scenes = json.loads((root / VERSION / "scene.json").read_text())
    a, b = scenes[1]["token"], scenes[0]["token"]
    _edit_table(
        "sample", lambda rs: [r.update(scene_token=b) for r in rs if r["scene_token"] == a]
    )(root, tmp)


def _empty_database(root: Path, tmp: Path) -> None:
    from radarslam.place_recognition.recognizer import PlaceRecognizer

    PlaceRecognizer().save(tmp / "empty.npz")


def _results_folder(root: Path, tmp: Path) -> None:
    from radarslam.geometry import se2_to_matrix
    from radarslam.slam.outputs import SessionResult, write_results

    t = 1_600_000_000_000_000 + np.arange(20, dtype=np.int64) * 500_000
    gt = np.stack([se2_to_matrix(0.8 * i, 0.0, 0.02 * i) for i in range(20)])
    write_results(tmp / "res", [SessionResult("scene-a", t, gt, gt, gt)], plots=False)


def _odometry_results_folder(root: Path, tmp: Path) -> None:
    from radarslam.geometry import se2_to_matrix
    from radarslam.io.results import write_results_folder, write_trajectories

    t = 1_600_000_000_000_000 + np.arange(20, dtype=np.int64) * 500_000
    gt = np.stack([se2_to_matrix(0.8 * i, 0.0, 0.02 * i) for i in range(20)])

    def contents(d: Path) -> None:
        write_trajectories(d, "scene-a", t, {"odometry": gt, "gt": gt})

    write_results_folder(tmp / "res", ["scene-a"], "odometry", contents, method="ours")


def _edit_run_json(**fields: object) -> Damage:
    def damage(root: Path, tmp: Path) -> None:
        run = tmp / "res" / "run.json"
        run.write_text(json.dumps({**json.loads(run.read_text()), **fields}))

    return damage


def _remove_results(*names: str) -> Damage:
    def damage(root: Path, tmp: Path) -> None:
        for name in names:
            (tmp / "res" / name).unlink()

    return damage


def _then(*damages: Damage) -> Damage:
    def damage(root: Path, tmp: Path) -> None:
        for d in damages:
            d(root, tmp)

    return damage


def _nothing(root: Path, tmp: Path) -> None:
    pass


ODO = "odometry --dataroot {root} --out {tmp}/out --no-progress"
RUN = "run --dataroot {root} --version v1.0-mini --out {tmp}/out --no-loops --no-progress"
STATS = "stats {root} --max-sweeps 3"
TINY_EGO = _radar_ego_poses(_scale_rotation(1e-8))
TINY_CS = _radar_calibrations(_scale_rotation(1e-8))

# (name, damage, command, expected piece of the error line)
CASES: list[tuple[str, Damage, str, str]] = [
    # ---- dataset files ---------------------------------------------------------------------------
    (
        "missing table",
        _remove(f"{VERSION}/ego_pose.json"),
        STATS,
        "ego_pose.json: table file is missing",
    ),
    ("truncated pcd header", _truncate_pcd_header, "stats {root}", ".pcd: truncated header"),
    (
        "no radar record, stats",
        _edit_table("sample_data", lambda records: records.clear()),
        STATS,
        "sample_data.json: no radar sample_data record",
    ),
    (
        "no radar record, odometry",
        _edit_table("sample_data", lambda records: records.clear()),
        ODO,
        "sample_data.json: no radar sample_data record",
    ),
    ("truncated pcd points", _truncate_pcd_points, "stats {root}", ".pcd: truncated"),
    ("truncated pcd, odometry", _truncate_pcd_points, ODO, ".pcd: truncated"),
    (
        "NaN ego translation",
        _radar_ego_poses(lambda r: r.update(translation=[float("nan"), 0.0, 0.0])),
        STATS,
        "has a non-finite translation",
    ),
    (
        "zero ego quaternion",
        _radar_ego_poses(lambda r: r.update(rotation=[0.0, 0.0, 0.0, 0.0])),
        STATS,
        "has a zero rotation quaternion",
    ),
    ("tiny ego quaternion, stats", TINY_EGO, STATS, "has norm 1e-08, not a rotation"),
    ("tiny ego quaternion, odometry", TINY_EGO, ODO, "has norm 1e-08, not a rotation"),
    ("tiny ego quaternion, run", TINY_EGO, RUN, "has norm 1e-08, not a rotation"),
    ("tiny calibration quaternion, stats", TINY_CS, STATS, "has norm 1e-08, not a rotation"),
    ("tiny calibration quaternion, odometry", TINY_CS, ODO, "has norm 1e-08, not a rotation"),
    ("tiny calibration quaternion, run", TINY_CS, RUN, "has norm 1e-08, not a rotation"),
    (
        "huge ego quaternion",
        _radar_ego_poses(_scale_rotation(1e300)),
        STATS,
        "has norm 1e+300, not a rotation",
    ),
    (
        "scene without samples, asked for",
        _no_samples_in_second_scene,
        STATS + " --scenes scene-0002",
        "scene 'scene-0002' has no samples",
    ),
    (
        "scene name not a string, run",
        _edit_table("scene", lambda rs: rs[0].update(name=5)),
        RUN,
        "scene.json: record '",
    ),
    (
        "sample next a list, odometry",
        _edit_table("sample", lambda rs: rs[0].update(next=["x"])),
        ODO,
        "field 'next' is ['x'], expected a string",
    ),
    (
        "scene name not a file name, odometry",
        _edit_table("scene", lambda rs: rs[0].update(name="../up")),
        ODO,
        "scene.json: session name '../up' cannot be used in file names",
    ),
    (
        "scene name not a file name, run",
        _edit_table("scene", lambda rs: rs[0].update(name="a/b")),
        RUN,
        "scene.json: session name 'a/b' cannot be used in file names",
    ),
    # ---- scene selection -------------------------------------------------------------------------
    ("empty --scenes, run", _nothing, RUN + " --scenes ''", "--scenes '': empty scene name"),
    ("empty --scenes, odometry", _nothing, ODO + " --scenes ''", "--scenes '': empty scene name"),
    ("empty --scenes, stats", _nothing, STATS + " --scenes ''", "--scenes '': empty scene name"),
    ("trailing comma in --scenes", _nothing, ODO + " --scenes scene-0001,", "empty scene name"),
    (
        "--scenes with --location",
        _nothing,
        RUN + " --scenes scene-0001 --location synth-seaport",
        "--scenes 'scene-0001' and --location 'synth-seaport': give one or the other",
    ),
    ("unknown scene", _nothing, ODO + " --scenes nope", "unknown scene 'nope'"),
    # ---- usage errors ----------------------------------------------------------------------------
    ("unknown dataset", _nothing, RUN + " --dataset foo", "Invalid value for '--dataset': 'foo'"),
    ("--max-scenes 0", _nothing, RUN + " --max-scenes 0", "Invalid value for '--max-scenes'"),
    ("unknown command", _nothing, "bogus", "No such command 'bogus'"),
    (
        "negative simulate seed",
        _nothing,
        "simulate --preset tiny --out {tmp}/sim --seed -1",
        "--seed -1: must be >= 0",
    ),
    # ---- settings --------------------------------------------------------------------------------
    (
        "unknown key",
        _nothing,
        ODO + " --set registration.voxel_size=1",
        "unknown key 'registration.voxel_size'",
    ),
    (
        "misspelled key in a config file",
        _write("typo.yaml", "registration:\n  voxel_sise_m: 1.0\n"),
        ODO + " --config {tmp}/typo.yaml",
        "typo.yaml: unknown key 'registration.voxel_sise_m'",
    ),
    (
        "duplicate key in a config file",
        _write("dup.yaml", "registration:\n  voxel_size_m: 1.0\n  voxel_size_m: 2.0\n"),
        ODO + " --config {tmp}/dup.yaml",
        "dup.yaml: line 3 invalid YAML (duplicate key 'voxel_size_m' (first given on line 2))",
    ),
    (
        "bad value type",
        _nothing,
        ODO + " --set fusion.mode=magic",
        "override 'fusion.mode=magic': 'fusion.mode'",
    ),
    *[
        (
            f"setting {key}={value}",
            _nothing,
            ODO + f" --set {key}={value}",
            f"override '{key}={value}': '{key}': {message}",
        )
        for key, value, message in [
            ("registration.fixed_sigma_m", "inf", "Input should be a finite number"),
            ("registration.fixed_sigma_m", "1e300", "Input should be less than or equal to 1000"),
            ("registration.fixed_sigma_m", "inf", "Input should be a finite number"),
            ("registration.voxel_size_m", "inf", "Input should be a finite number"),
            ("doppler.noise_floor_mps", "inf", "Input should be a finite number"),
            ("doppler.noise_floor_mps", "1e300", "Input should be less than or equal to 1000"),
            ("doppler.inlier_threshold_mps", "nan", "Input should be a finite number"),
            ("doppler.seed", "-1", "Input should be greater than or equal to 0"),
            (
                "fusion.icp_along_track_sigma_fraction",
                "1e300",
                "Input should be less than or equal to 1000",
            ),
        ]
    ],
    (
        "static map voxel inf",
        _nothing,
        RUN + " --set backend.static_map.voxel_size_m=inf",
        "'backend.static_map.voxel_size_m': Input should be a finite number",
    ),
    (
        "negative seed in simulate --set",
        _nothing,
        "simulate --preset tiny --out {tmp}/sim --set seed=-1",
        "'seed': Input should be greater than or equal to 0",
    ),
    # ---- outputs ---------------------------------------------------------------------------------
    (
        "output is a file, odometry",
        _write("afile", "keep me"),
        "odometry --dataroot {root} --out {tmp}/afile --no-progress",
        "afile: cannot create results folder",
    ),
    (
        "output under a file, run",
        _write("afile", "keep me"),
        "run --dataroot {root} --out {tmp}/afile/res --no-progress",
        "afile/res: cannot create results folder",
    ),
    (
        "output is the dataroot",
        _nothing,
        "run --dataroot {root} --out {root} --no-loops --no-progress",
        "which is not a result file; a results folder is replaced as a whole",
    ),
    # ---- results folders, databases --------------------------------------------------------------
    (
        "eval: folder without run.json",
        _then(_results_folder, _remove_results("run.json")),
        "eval {tmp}/res --no-plots",
        "no run.json: not a complete results folder",
    ),
    (
        "eval: SLAM poses missing",
        _then(
            _results_folder,
            lambda root, tmp: [
                (tmp / "res" / f"poses_scene-a.{x}").unlink() for x in ("tum", "kitti")
            ],
        ),
        "eval {tmp}/res --no-plots",
        "poses_scene-a.tum: missing (run.json lists session 'scene-a')",
    ),
    (
        "eval: odometry folder without its odometry poses",
        _then(
            _odometry_results_folder,
            _remove_results("odometry_scene-a.tum", "odometry_scene-a.kitti"),
        ),
        "eval {tmp}/res --no-plots",
        "odometry_scene-a.tum: missing (run.json lists session 'scene-a')",
    ),
    (
        "eval: unknown kind of results folder",
        _then(_odometry_results_folder, _edit_run_json(kind="lidar")),
        "eval {tmp}/res --no-plots",
        "run.json: 'kind' must be one of slam, odometry, got 'lidar'",
    ),
    (
        "corrupt checkpoint",
        _write("bad.pt", "not a checkpoint"),
        "run --dataroot {root} --out {tmp}/out --checkpoint {tmp}/bad.pt --no-progress",
        "bad.pt: not a radarslam checkpoint",
    ),
    (
        "place database given as the checkpoint",
        _then(_empty_database, lambda root, tmp: (tmp / "empty.npz").rename(tmp / "db.pt")),
        "pr build-db --dataroot {root} --out {tmp}/db.npz --checkpoint {tmp}/db.pt",
        "db.pt: not a radarslam checkpoint (a zip archive, but not torch's: holds ",
    ),
    (
        "pr query: empty database",
        _empty_database,
        "pr query {tmp}/empty.npz --dataroot {root} --version v1.0-mini --scenes scene-0001",
        "empty.npz: the database holds no places",
    ),
    (
        "pr query: corrupt database",
        _write("corrupt.npz", "not a database"),
        "pr query {tmp}/corrupt.npz --dataroot {root} --version v1.0-mini --scenes scene-0001",
        "corrupt.npz",
    ),
    (
        "pr build-db: --scenes with --location",
        _nothing,
        "pr build-db --dataroot {root} --version v1.0-mini --out {tmp}/db.npz --scenes scene-0001 "
        "--location synth-seaport",
        "--scenes 'scene-0001' and --location 'synth-seaport': give one or the other",
    ),
]


# ---- the test ------------------------------------------------------------------------------------
def _fresh_copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst, copy_function=os.link, ignore=shutil.ignore_patterns(VERSION))
    shutil.copytree(src / VERSION, dst / VERSION)
    return dst


def _digest(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.md5(p.read_bytes()).hexdigest()
        for p in sorted(folder.rglob("*"))
        if p.is_file()
    }


@pytest.mark.parametrize(
    ("name", "damage", "command", "expected"), CASES, ids=[c[0] for c in CASES]
)
def test_bad_input_is_one_error_line(
    tiny_dataroot, tmp_path, run_cli, name, damage, command, expected
):
    root = _fresh_copy(tiny_dataroot, tmp_path / "data")
    damage(root, tmp_path)
    before = _digest(tmp_path)
    argv = shlex.split(command.format(root=root, tmp=tmp_path))
    code, err = run_cli(argv)
    errors = [line for line in err.splitlines() if line.startswith("error:")]
    assert code == 2, err
    assert len(errors) == 1 and err.rstrip("\n").endswith(errors[0]), err
    assert expected in errors[0], errors[0]
    assert "Traceback" not in err
    after = _digest(tmp_path)
    assert {k: v for k, v in after.items() if k in before} == before  # no input file changed


def test_a_broken_scene_does_not_block_the_others(tiny_dataroot, tmp_path, run_cli):
    root = _fresh_copy(tiny_dataroot, tmp_path / "data")
    _no_samples_in_second_scene(root, tmp_path)
    code, err = run_cli(shlex.split(STATS.format(root=root) + " --scenes scene-0001"))
    assert code == 0, err


def test_a_bad_demo_preset_makes_no_folder(tmp_path, run_cli):
    out = tmp_path / "demo"
    code, err = run_cli(["demo", "--preset", "bogus", "--out", str(out), "--no-progress"])
    errors = [line for line in err.splitlines() if line.startswith("error:")]
    assert code == 2 and len(errors) == 1 and "unknown simulation preset 'bogus'" in errors[0]
    assert not out.exists()
