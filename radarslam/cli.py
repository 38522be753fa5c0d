"""The ``radarslam`` command line.

Command modules are imported here but keep heavy libraries (torch, open3d, gtsam, kiss_icp) inside
their function bodies, so ``radarslam --help`` stays instant.
"""

from __future__ import annotations

import sys

import typer

from radarslam.errors import RadarSlamError

try:  # typer >= 0.2x ships its own copy of click
    from typer._click import exceptions as _click_exceptions
except ImportError:  # pragma: no cover
    from click import exceptions as _click_exceptions  # type: ignore[no-redef]

app = typer.Typer(
    name="radarslam",
    help="Radar SLAM for nuScenes-style automotive radar (5x Continental ARS408).",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)

# --- command registration (each module is light at import time) -------------------------------
# BEGIN COMMANDS
from radarslam.eval import commands as _eval_commands  # noqa: E402
from radarslam.nuscenes import commands as _nuscenes_commands  # noqa: E402
from radarslam.odometry import commands as _odometry_commands  # noqa: E402
from radarslam.place_recognition.commands import pr_app  # noqa: E402
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


def _usage_error_line(exc) -> str:
    """One line for a click/typer usage error (bad option value, unknown command, missing
    option): typer would draw a multi-line box."""
    msg = " ".join(exc.format_message().split()).replace("Value error, ", "").rstrip(".")
    ctx = getattr(exc, "ctx", None)
    where = f"; see '{ctx.command_path} --help'" if ctx is not None else ""
    return f"error: {msg}{where}"


def _exit_interrupted() -> None:
    """``interrupted`` on stderr, exit status 130. What is left to do then is the interpreter's
    shutdown (the exit handlers, multiprocessing's last join among them): a further Ctrl-C
    there would only print "Exception ignored" tracebacks, so the first exit handler to run
    ignores it from then on."""
    import atexit
    import signal

    def ignore_ctrl_c() -> None:
        try:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
        except ValueError:  # not the main thread
            pass

    atexit.register(ignore_ctrl_c)  # registered last, run first
    print("interrupted", file=sys.stderr)
    sys.exit(130)


def main() -> None:
    """Console entry point: user errors become one line on stderr and exit status 2.

    Usage errors (a bad option value, an unknown command or option, a missing option), a
    :class:`RadarSlamError` raised by a command and an OSError no command turned into one are
    each printed as one ``error:`` line; an interruption (Ctrl-C or SIGTERM) prints
    ``interrupted`` and exits with status 130, also where the interrupt surfaced as another
    exception (a compiled module whose import was cut short raises ImportError from it).
    """
    _install_sigterm_handler()
    try:
        # not standalone: usage errors reach this handler instead of typer's box
        code = app(standalone_mode=False)
    except _click_exceptions.NoArgsIsHelpError:  # the help is already shown
        sys.exit(2)
    except _click_exceptions.ClickException as exc:
        print(_usage_error_line(exc), file=sys.stderr)
        sys.exit(2)
    except typer.Abort as exc:  # end of input at a prompt
        if _was_interrupted(exc):
            _exit_interrupted()
        print("aborted", file=sys.stderr)
        sys.exit(1)
    except KeyboardInterrupt:
        _exit_interrupted()
    except SystemExit as exc:
        if exc.code == 130 and _was_interrupted(exc):
            _exit_interrupted()
        raise
    except Exception as exc:
        if _was_interrupted(exc):
            _exit_interrupted()
        if isinstance(exc, RadarSlamError):
            print(f"error: {exc}", file=sys.stderr)
            sys.exit(2)
        if isinstance(exc, OSError):
            where = f"{exc.filename}: " if exc.filename is not None else ""
            print(f"error: {where}{exc.strerror or exc}", file=sys.stderr)
            sys.exit(2)
        raise
    # typer's non-standalone mode returns an exit code instead of exiting: 130 is its
    # KeyboardInterrupt, 0 a --help
    if isinstance(code, int) and not isinstance(code, bool) and code != 0:
        if code == 130:
            _exit_interrupted()
        sys.exit(code)


if __name__ == "__main__":  # python -m radarslam.cli
    main()
