"""What every benchmark script does with a user error: one line, exit status 2."""

from __future__ import annotations

import importlib.util
import sys
from collections.abc import Callable
from pathlib import Path
from types import ModuleType


def guarded(main: Callable[[], object]) -> None:
    """Run ``main``; a :class:`~radarslam.errors.RadarSlamError` (a bad ``--set``, a missing
    or malformed dataroot, a bad checkpoint) prints ``error: <message>`` and exits with 2."""
    from radarslam.errors import RadarSlamError

    try:
        code = main()
    except RadarSlamError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)
    if isinstance(code, int) and code:
        sys.exit(code)


def sibling_bench(script: str) -> ModuleType:
    """Another benchmark script of this folder (``odometry`` for bench/odometry.py), imported as
    ``bench_<script>``: a pool's workers unpickle its functions by that module name."""
    name = f"bench_{script}"
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, Path(__file__).with_name(f"{script}.py"))
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[name] = mod
    spec.loader.exec_module(mod)
    return mod
