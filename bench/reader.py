"""Benchmark of the nuScenes radar reader (a script printing tables, not a test).

1. Sweep decoding: ``read_pcd`` + :class:`RadarPointFilter` vs the devkit's
   ``RadarPointCloud.from_file`` on the same 125-point files (sweeps/s and the ratio).
2. Table start-up on a fake large table set (``--records`` sample_data records, nuScenes-like mix
   of radar / camera / lidar, one ego pose each, in the indent=0 layout of the real files): time and
   peak RSS of a fresh process that builds the radar index, then of one that loads it from the
   cache, beside the peer ``json.load`` of ``sample_data.json`` + ``ego_pose.json`` (what the
   devkit's ``NuScenes`` does at start-up).

Usage: ``python bench/reader.py [--records 1500000] [--files 400] [--workdir DIR]
[--reuse-tables] [--no-json-peer]``
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from radarslam.nuscenes.filters import RadarPointFilter
from radarslam.nuscenes.pcd import pcd_bytes, read_pcd
from radarslam.types import RADAR_CHANNELS, RADAR_DTYPE

CAMS = (
    "CAM_FRONT",
    "CAM_FRONT_LEFT",
    "CAM_FRONT_RIGHT",
    "CAM_BACK",
    "CAM_BACK_LEFT",
    "CAM_BACK_RIGHT",
)
VERSION = "v1.0-trainval"


def _tok(i: int, kind: str) -> str:
    return f"{kind}{i:030x}"[-32:]


def random_points(rng: np.random.Generator, n: int = 125) -> np.ndarray:
    pts = np.zeros(n, dtype=RADAR_DTYPE)
    r, a = rng.uniform(1, 200, n), rng.uniform(-1.0, 1.0, n)
    pts["x"], pts["y"] = r * np.cos(a), r * np.sin(a)
    for f in ("rcs", "vx", "vy", "vx_comp", "vy_comp"):
        pts[f] = rng.normal(0, 5, n)
    pts["dyn_prop"] = rng.choice(
        [0, 1, 2, 3, 4, 5, 6, 7], n, p=[0.05, 0.5, 0.02, 0.3, 0.05, 0.03, 0.02, 0.03]
    )
    pts["invalid_state"] = rng.choice([0, 4, 9, 11, 16], n, p=[0.58, 0.1, 0.1, 0.12, 0.1])
    pts["ambig_state"] = rng.choice([1, 2, 3, 4], n, p=[0.03, 0.03, 0.9, 0.04])
    pts["id"] = np.arange(n)
    pts["pdh0"] = 1
    return pts


# ------------------------------------------------------------------------------------------------
def bench_decoding(workdir: Path, n_files: int) -> list[tuple[str, float, str]]:
    rng = np.random.default_rng(0)
    folder = workdir / "pcd"
    folder.mkdir(parents=True, exist_ok=True)
    files = []
    for i in range(n_files):
        p = folder / f"n015__RADAR_FRONT__{1_532_402_000_000_000 + i * 76_923}.pcd"
        p.write_bytes(pcd_bytes(random_points(rng), padding=int(rng.integers(1, 4000))))
        files.append(p)
    flt = RadarPointFilter.devkit_default()

    def ours():
        return sum(len(flt.apply(read_pcd(p))) for p in files)

    rows = []
    t_ours, kept_ours = _best(ours)
    rows.append(
        ("radarslam read_pcd + devkit_default filter", n_files / t_ours, f"{kept_ours} pts")
    )
    try:
        from nuscenes.utils.data_classes import RadarPointCloud
    except ImportError:
        rows.append(("nuscenes-devkit RadarPointCloud.from_file", float("nan"), "not installed"))
        return rows
    strs = [str(p) for p in files]

    def devkit():
        return sum(RadarPointCloud.from_file(s).nbr_points() for s in strs)

    t_dev, kept_dev = _best(devkit, repeat=2)
    rows.append(("nuscenes-devkit RadarPointCloud.from_file", n_files / t_dev, f"{kept_dev} pts"))
    rows.append(
        (
            "ratio (ours / devkit)",
            t_dev / t_ours,
            "same points" if kept_dev == kept_ours else "DIFFER",
        )
    )
    return rows


def _best(fn, repeat: int = 3):
    best, out = float("inf"), None
    for _ in range(repeat):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


# ------------------------------------------------------------------------------------------------
SD_TEMPLATE = (
    '{sep}{{\n"token": "{token}",\n"sample_token": "{sample}",\n"ego_pose_token": "{ego}",\n'
    '"calibrated_sensor_token": "{cs}",\n"timestamp": {ts},\n"fileformat": "{fmt}",\n'
    '"is_key_frame": {key},\n"height": 0,\n"width": 0,\n'
    '"filename": "{folder}/{ch}/n015-2018-07-24-11-22-45+0800__{ch}__{ts}.{ext}",\n'
    '"prev": "{prev}",\n"next": "{next}"\n}}'
)
EGO_TEMPLATE = (
    '{sep}{{\n"token": "{token}",\n"timestamp": {ts},\n"rotation": [0.5720320396729045, '
    "-0.0016977771610471074, 0.011798001930183783, -0.8201446642457809],\n"
    '"translation": [{x}, {y}, 0.0]\n}}'
)


def _modality(ch: str) -> str:
    return "radar" if ch.startswith("RADAR") else "camera" if ch.startswith("CAM") else "lidar"


def write_fake_tables(root: Path, n_records: int) -> dict[str, int]:
    """A v1.0-trainval-sized table set (JSON only: no .pcd files are needed to index)."""
    vdir = root / VERSION
    vdir.mkdir(parents=True, exist_ok=True)
    n_scenes = max(1, n_records // 3100)  # ~3.1k sample_data per scene, as in trainval
    per_scene = n_records // n_scenes
    # per scene and 20 s: 5 radars x 260, 6 cameras x 240, lidar 400 -> radar ~ 41 %
    mix = [(ch, 260) for ch in RADAR_CHANNELS] + [(c, 240) for c in CAMS] + [("LIDAR_TOP", 400)]
    total_w = sum(w for _, w in mix)
    counts = [(ch, max(1, per_scene * w // total_w)) for ch, w in mix]
    logs = [
        {
            "token": _tok(0, "log"),
            "logfile": "fake",
            "vehicle": "n015",
            "date_captured": "2018-07-24",
            "location": "boston-seaport",
        }
    ]
    sensors = [
        {"token": _tok(i, "sen"), "channel": ch, "modality": _modality(ch)}
        for i, (ch, _) in enumerate(mix)
    ]
    cs = [
        {
            "token": _tok(i, "cs"),
            "sensor_token": s["token"],
            "translation": [1.0, 0.0, 0.5],
            "rotation": [1.0, 0.0, 0.0, 0.0],
            "camera_intrinsic": [],
        }
        for i, s in enumerate(sensors)
    ]
    scenes, samples = [], []
    n_sd = n_radar = 0
    with (vdir / "sample_data.json").open("w") as f_sd, (vdir / "ego_pose.json").open("w") as f_ego:
        f_sd.write("[\n")
        f_ego.write("[\n")
        sep = ""
        for s in range(n_scenes):
            t0 = 1_532_402_000_000_000 + s * 30_000_000
            scene_tok = _tok(s, "scn")
            s_toks = [_tok(s * 100 + k, "smp") for k in range(40)]
            for k, st in enumerate(s_toks):
                samples.append(
                    {
                        "token": st,
                        "timestamp": t0 + k * 500_000,
                        "prev": s_toks[k - 1] if k else "",
                        "next": s_toks[k + 1] if k < 39 else "",
                        "scene_token": scene_tok,
                    }
                )
            scenes.append(
                {
                    "token": scene_tok,
                    "log_token": logs[0]["token"],
                    "nbr_samples": 40,
                    "first_sample_token": s_toks[0],
                    "last_sample_token": s_toks[-1],
                    "name": f"scene-{s:04d}",
                    "description": "",
                }
            )
            for ci, (ch, n) in enumerate(counts):
                period = 20_000_000 // n
                ext = {"radar": "pcd", "camera": "jpg", "lidar": "pcd.bin"}[_modality(ch)]
                for k in range(n):
                    i = n_sd + k
                    ts = t0 + k * period
                    key = k % max(1, n // 40) == 0
                    f_sd.write(
                        SD_TEMPLATE.format(
                            sep=sep,
                            token=_tok(i, "sd"),
                            sample=s_toks[min(39, k * 40 // n)],
                            ego=_tok(i, "ep"),
                            cs=cs[ci]["token"],
                            ts=ts,
                            fmt=ext.split(".")[0],
                            key=str(key).lower(),
                            folder="samples" if key else "sweeps",
                            ch=ch,
                            ext=ext,
                            prev=_tok(i - 1, "sd") if k else "",
                            next=_tok(i + 1, "sd") if k < n - 1 else "",
                        )
                    )
                    f_ego.write(
                        EGO_TEMPLATE.format(
                            sep=sep,
                            token=_tok(i, "ep"),
                            ts=ts,
                            x=411.30393 + k * 0.4,
                            y=1180.89 + s,
                        )
                    )
                    sep = ",\n"
                n_sd += n
                if ch.startswith("RADAR"):
                    n_radar += n
        f_sd.write("\n]")
        f_ego.write("\n]")
    small = {"scene": scenes, "sample": samples, "log": logs, "sensor": sensors}
    small["calibrated_sensor"] = cs
    for name, recs in small.items():
        (vdir / f"{name}.json").write_text(json.dumps(recs, indent=0))
    size = sum((vdir / f"{n}.json").stat().st_size for n in ("sample_data", "ego_pose"))
    return {"sample_data": n_sd, "radar": n_radar, "scenes": n_scenes, "bytes": size}


# peak RSS from /proc (VmHWM): ru_maxrss survives exec and would report the parent's peak
HWM = "int([ln for ln in open('/proc/self/status') if ln.startswith('VmHWM')][0].split()[1]) / 1024"
CHILD_INDEX = """
import sys, time
t0 = time.perf_counter()
from radarslam.nuscenes.tables import NuScenesTables
t = NuScenesTables(sys.argv[1], "v1.0-trainval", cache_dir=sys.argv[2], cache_min_bytes=0)
n = len(t.radar); _ = t.radar_tokens.find("x")
print(time.perf_counter() - t0, HWM, n, t.cache_hit)
""".replace("HWM", HWM)
CHILD_JSON = """
import json, sys, time
t0 = time.perf_counter()
sd = json.load(open(sys.argv[1] + "/v1.0-trainval/sample_data.json"))
ep = json.load(open(sys.argv[1] + "/v1.0-trainval/ego_pose.json"))
print(time.perf_counter() - t0, HWM, len(sd), len(ep))
""".replace("HWM", HWM)


def _child(code: str, *args: str) -> list[str]:
    out = subprocess.run(
        [sys.executable, "-c", code, *args], capture_output=True, text=True, timeout=1800
    )
    if out.returncode != 0:
        raise SystemExit(f"child failed: {out.stderr.strip().splitlines()[-1:]}")
    return out.stdout.split()


def bench_startup(
    workdir: Path, n_records: int, with_json_peer: bool, reuse: bool = False
) -> list[tuple]:
    root = workdir / "fake_nuscenes"
    t0 = time.perf_counter()
    meta = root / "tables.json"
    if reuse and meta.is_file() and json.loads(meta.read_text())["requested"] == n_records:
        info = json.loads(meta.read_text())
    else:
        info = write_fake_tables(root, n_records)
        meta.write_text(json.dumps({**info, "requested": n_records}))
    t_write = time.perf_counter() - t0
    print(
        f"wrote {info['sample_data']:,} sample_data records ({info['radar']:,} radar, "
        f"{info['scenes']} scenes, {info['bytes'] / 2**20:.0f} MiB of sample_data + ego_pose "
        f"JSON) in {t_write:.0f} s",
        flush=True,
    )
    cache = workdir / "cache"
    shutil.rmtree(cache, ignore_errors=True)
    rows = []
    cold = _child(CHILD_INDEX, str(root), str(cache))
    rows.append(
        (
            "radarslam index, first start (builds + writes cache)",
            float(cold[0]),
            float(cold[1]),
            cold[2],
        )
    )
    warm = _child(CHILD_INDEX, str(root), str(cache))
    assert warm[3] == "True", warm
    rows.append(("radarslam index, cached start", float(warm[0]), float(warm[1]), warm[2]))
    if with_json_peer:
        js = _child(CHILD_JSON, str(root))
        rows.append(
            ("peer: json.load sample_data + ego_pose (devkit)", float(js[0]), float(js[1]), js[2])
        )
    base = _child(f"import numpy, radarslam.nuscenes.tables; print({HWM})")
    rows.append(("(python + numpy + radarslam imports only)", float("nan"), float(base[0]), "-"))
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--records", type=int, default=1_500_000, help="fake sample_data records")
    ap.add_argument("--files", type=int, default=400, help=".pcd files for the decoding benchmark")
    ap.add_argument("--workdir", type=Path, default=None)
    ap.add_argument("--keep", action="store_true", help="keep the generated files")
    ap.add_argument("--no-json-peer", action="store_true", help="skip the json.load peer run")
    ap.add_argument(
        "--reuse-tables", action="store_true", help="reuse fake tables left in --workdir"
    )
    args = ap.parse_args()
    workdir = args.workdir or Path(tempfile.mkdtemp(prefix="radarslam_bench_"))
    try:
        print("\n## Sweep decoding (125-point radar .pcd files)\n")
        print("| reader | sweeps/s | kept |\n|---|---|---|")
        for name, rate, note in bench_decoding(workdir, args.files):
            print(
                f"| {name} | {rate:,.1f} | {note} |"
                if "ratio" not in name
                else f"| {name} | {rate:.1f}x | {note} |"
            )
        print(
            f"\n## Table start-up, {args.records:,} fake sample_data records (fresh process each)\n"
        )
        rows = bench_startup(workdir, args.records, not args.no_json_peer, args.reuse_tables)
        print("| run | time (s) | peak RSS (MiB) | radar records / records |\n|---|---|---|---|")
        for name, t, rss, n in rows:
            ts = "-" if t != t else f"{t:.2f}"
            print(f"| {name} | {ts} | {rss:,.0f} | {n} |")
    finally:
        if not args.keep and args.workdir is None:
            shutil.rmtree(workdir, ignore_errors=True)


if __name__ == "__main__":
    from _cli import guarded

    guarded(main)
