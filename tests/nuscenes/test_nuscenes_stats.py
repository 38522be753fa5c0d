"""Dataset statistics and the ``radarslam stats`` command on the hand-made dataroot."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from radarslam.nuscenes import commands
from radarslam.nuscenes.filters import RadarPointFilter
from radarslam.nuscenes.pcd import read_pcd
from radarslam.nuscenes.stats import REAL_NUSCENES, dataset_statistics


def test_statistics_pinned_and_independent(mini, reader):
    st = dataset_statistics(reader, progress=False)
    assert (st.num_scenes, st.num_sweeps, st.num_points) == (4, 769, 42929)  # pinned
    assert (st.empty_sweeps, st.nan_points) == (2, 3)
    # independent recount from the files
    pts = np.concatenate([read_pcd(p) for p in sorted(mini.dataroot.rglob("*.pcd"))])
    pts = pts[np.isfinite(pts["vx_comp"])]
    assert len(pts) == st.num_points
    assert st.filtered_fraction == pytest.approx(
        RadarPointFilter.devkit_default().mask(pts).mean(), abs=1e-12
    )
    xy = np.column_stack([pts["x"], pts["y"]]).astype(float)
    u = xy / np.linalg.norm(xy, axis=1, keepdims=True)
    vr_comp = np.abs((u * np.column_stack([pts["vx_comp"], pts["vy_comp"]])).sum(1))
    assert st.moving_fraction == pytest.approx((vr_comp > 1.0).mean(), abs=1e-12)
    assert st.range_percentiles_m["p50"] == pytest.approx(np.median(np.hypot(xy[:, 0], xy[:, 1])))
    assert st.invalid_state_hist[0] == pytest.approx((pts["invalid_state"] == 0).mean())
    assert sum(st.dyn_prop_hist.values()) == pytest.approx(1.0)
    # the synthetic files satisfy the Doppler oracle exactly, like real ones
    assert st.doppler_oracle_rms_p95_mps < 1e-5
    # exact static landmarks: nearly all re-detected (misses are FOV/range exits)
    assert st.redetect_next == pytest.approx(0.99004, abs=1e-4)
    assert st.redetect_within_3 >= st.redetect_next
    md = st.to_markdown()
    assert "| statistic | measured | real nuScenes |" in md
    assert REAL_NUSCENES["tangential_p50_mps"] in md and "2 / 3" in md
    assert json.loads(st.to_json())["num_sweeps"] == 769


def test_statistics_detect_a_broken_oracle_and_cap(mini, clone):
    from radarslam.nuscenes.reader import NuScenesRadar

    root = clone(copy_files=True)
    tok = mini.sweeps[("scene-0003", "RADAR_FRONT")][0]
    r = NuScenesRadar(root, "v1.0-mini", use_cache=False)
    path = root / r.load_sweep(tok).filename
    from radarslam.nuscenes.pcd import write_pcd

    pts = read_pcd(path)
    # per-point errors cannot be one sensor velocity (a constant offset could): the oracle breaks
    pts["vx_comp"] += np.random.default_rng(0).normal(0.0, 1.0, len(pts)).astype(np.float32)
    write_pcd(path, pts)
    st = dataset_statistics(r, scenes=["scene-0003"], max_sweeps_per_scene=2, progress=False)
    assert st.num_sweeps == 10
    assert st.doppler_oracle_rms_p95_mps > 0.3  # 1 broken sweep of 10


def _app() -> typer.Typer:
    app = typer.Typer()
    app.callback()(lambda: None)  # force sub-command mode, as in radarslam.cli
    app.command("stats")(commands.stats)
    return app


def test_stats_command(mini, tmp_path):
    out = tmp_path / "s.json"
    res = CliRunner().invoke(
        _app(),
        ["stats", str(mini.dataroot), "--scenes", "scene-0001,scene-0003", "--max-sweeps", "5",
         "--json", str(out)],
    )  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "| range p50 (m) |" in res.output
    data = json.loads(out.read_text())
    assert data["num_scenes"] == 2 and data["num_sweeps"] == 50


def test_cli_module_stays_light():
    code = (
        "import sys, radarslam.cli; "
        "heavy = [m for m in ('numpy', 'torch', 'radarslam.nuscenes.reader') if m in sys.modules]; "
        "print(heavy)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert "radarslam.nuscenes.reader" not in out.stdout and "torch" not in out.stdout
