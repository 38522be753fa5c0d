"""``radarslam eval`` interrupted while it writes: metrics.json and the plots stay the previous
ones, all of them, or are all new."""

from __future__ import annotations

import json
import os
import signal

import numpy as np
import pytest

from radarslam.eval.commands import eval_command
from radarslam.geometry import se2_to_matrix
from radarslam.slam.outputs import SessionResult, write_results


def _snapshot(d):
    return {
        p.relative_to(d).as_posix(): p.read_bytes() for p in sorted(d.rglob("*")) if p.is_file()
    }


@pytest.fixture
def evaluated(tmp_path):
    ts = 1_000_000 + np.arange(40, dtype=np.int64) * 500_000
    gt = np.stack([se2_to_matrix(float(i), 0.1 * i, 0.01 * i) for i in range(40)])
    est = np.stack([p @ se2_to_matrix(0.05, -0.05, 0.001) for p in gt])
    out = tmp_path / "res"
    write_results(out, [SessionResult("a", ts, est, est, gt)], loops=[], plots=False)
    eval_command(out, override=["rpe_distance_m=5"])
    assert json.loads((out / "metrics.json").read_text())["config"]["rpe_distance_m"] == 5.0
    return out


@pytest.mark.parametrize("at", ["trajectories", "errors"])
def test_ctrl_c_while_eval_writes_leaves_the_previous_metrics_and_plots(evaluated, monkeypatch, at):
    from radarslam.eval import plots

    before = _snapshot(evaluated)
    assert {"metrics.json", "plots/trajectories.png", "plots/errors_a.png"} <= set(before)
    name = "plot_trajectories" if at == "trajectories" else "plot_errors_over_time"
    real = getattr(plots, name)

    def interrupted(*args, **kwargs):
        real(*args, **kwargs)  # this plot is written (to its temporary file), then Ctrl-C
        os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(plots, name, interrupted)
    with pytest.raises(KeyboardInterrupt):
        eval_command(evaluated, override=["rpe_distance_m=7"])
    assert _snapshot(evaluated) == before
    assert sorted(p.name for p in evaluated.rglob(".*")) == []  # no temporary file left
    monkeypatch.undo()
    eval_command(evaluated, override=["rpe_distance_m=7"])
    after = _snapshot(evaluated)
    assert set(after) == set(before) and after["metrics.json"] != before["metrics.json"]
