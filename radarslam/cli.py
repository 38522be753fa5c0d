"""The ``radarslam`` command line.

Command modules are imported here but keep heavy libraries (torch, open3d, gtsam, kiss_icp) inside
their function bodies, so ``radarslam --help`` stays instant.
"""

from __future__ import annotations

import sys

import typer

from radarslam.errors import RadarSlamError

app = typer.Typer(
    name="radarslam",
    help="Radar SLAM for nuScenes-style automotive radar (5x Continental ARS408).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

# --- command registration (each module is light at import time) -------------------------------
# BEGIN COMMANDS
from place_recognition.commands import pr_app  # noqa: E402
from radarslam.eval import commands as _eval_commands  # noqa: E402
from radarslam.nuscenes import commands as _nuscenes_commands  # noqa: E402
from radarslam.odometry import commands as _odometry_commands  # noqa: E402
from radarslam.sim import commands as _sim_commands  # noqa: E402
from radarslam.slam import commands as _slam_commands  # noqa: E402

app.command("demo")(_slam_commands.demo_command)
app.command("run")(_slam_commands.run_command)
app.command("eval")(_eval_commands.eval_command)
app.command("odometry")(_odometry_commands.odometry)
app.command("simulate")(_sim_commands.simulate_command)
app.command("stats")(_nuscenes_commands.stats)
app.add_typer(pr_app, name="pr")
# END COMMANDS


def main() -> None:
    """Console entry point: user errors become one line on stderr and exit status 2.

    typer's standalone mode already turns usage errors into a usage line (exit 2); what reaches
    this handler is a :class:`RadarSlamError` raised by a command.
    """
    try:
        app()
    except RadarSlamError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
