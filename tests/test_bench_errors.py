"""The benchmark scripts answer a bad argument with one line and exit status 2, like the CLI."""

import subprocess
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench"


@pytest.mark.parametrize(
    ("script", "args", "names"),
    [
        ("odometry.py", ["--set", "fusion.gate_chi2=-1"], "fusion.gate_chi2"),
        ("odometry.py", ["--set", "foo.bar=1"], "foo"),
        # before generating the (missing) city: nothing is written
        (
            "slam.py",
            ["--set", "loops.no_such_key=1", "--dataroot", "{tmp}/city", "--out", "{tmp}/out"],
            "no_such_key",
        ),
        ("odometry.py", ["--dataroot", "{tmp}/none"], "no such folder"),
        ("realism.py", ["--set", "world.x=1", "--work", "{tmp}/work"], "world"),
    ],
)
def test_bad_argument_is_one_line_and_status_2(tmp_path, script, args, names):
    args = [a.replace("{tmp}", str(tmp_path)) for a in args]
    out = subprocess.run(
        [sys.executable, str(BENCH / script), *args], capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 2, out.stderr
    lines = [ln for ln in out.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and names in lines[0], out.stderr
    assert not list(tmp_path.iterdir())  # nothing written
