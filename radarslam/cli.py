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


def _raise_interrupt(signum, frame) -> None:
    """SIGTERM handler: behave like Ctrl-C, so atomic writes remove their temporary files."""
    import os
    import signal

    if os.getpid() != _MAIN_PID:  # a forked worker inherited it: die the default way
        signal.signal(signum, signal.SIG_DFL)
        os.kill(os.getpid(), signum)
        return
    raise KeyboardInterrupt


_MAIN_PID: int | None = None


def _install_sigterm_handler() -> None:
    import os
    import signal

    global _MAIN_PID
    _MAIN_PID = os.getpid()
    try:
        signal.signal(signal.SIGTERM, _raise_interrupt)
    except ValueError:  # not the main thread: leave SIGTERM alone
        pass


def _was_interrupted(exc: BaseException) -> bool:
    """Whether typer turned a KeyboardInterrupt into this exit (it exits 130 silently)."""
    seen: set[int] = set()
    e: BaseException | None = exc
    while e is not None and id(e) not in seen:
        if isinstance(e, KeyboardInterrupt):
            return True
        seen.add(id(e))
        e = e.__cause__ or e.__context__
    return False


def main() -> None:
    """Console entry point: user errors become one line on stderr and exit status 2.

    typer's standalone mode already turns usage errors into a usage line (exit 2); what reaches
    this handler is a :class:`RadarSlamError` raised by a command, an OSError no command turned
    into one (printed as one line too), or an interruption: Ctrl-C or SIGTERM print
    ``interrupted`` and exit with status 130.
    """
    _install_sigterm_handler()
    try:
        app()
    except RadarSlamError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
    except SystemExit as exc:
        if exc.code == 130 and _was_interrupted(exc):
            print("interrupted", file=sys.stderr)
        raise
    except OSError as exc:
        where = f"{exc.filename}: " if exc.filename is not None else ""
        print(f"error: {where}{exc.strerror or exc}", file=sys.stderr)
        sys.exit(2)
