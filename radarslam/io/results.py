"""The results folder (layout: docs/outputs.md): written by ``radarslam run`` (SLAM) and
``radarslam odometry``, read by ``radarslam eval``. This module holds what writer and reader share:
the file names, the check of a folder about to be replaced, the writing of trajectories and
``run.json``, and the reading of a folder back.

A folder is of one of two kinds (``run.json``'s ``kind``): ``slam`` (SLAM, odometry and ground
truth per key frame, loops, map) or ``odometry`` (odometry and ground truth per radar frame,
key-frame motions; ``method`` names the odometry). A ``run.json`` without ``kind`` is ``slam``.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from radarslam.errors import DataError
from radarslam.io.atomic import atomic_folder, check_output_folder, write_json_atomic
from radarslam.io.text import read_text
from radarslam.io.trajectory import read_kitti, read_tum, write_kitti, write_tum

log = logging.getLogger("radarslam.io")

#: The ``format`` tag of ``run.json``.
RESULTS_FORMAT = "radarslam-results/1"
#: The kinds of results folder (``run.json``'s ``kind``).
RESULT_KINDS = ("slam", "odometry")
#: File name prefix of each trajectory: ``<prefix><session>.tum`` and ``.kitti``.
TRAJECTORY_PREFIX = {"slam": "poses_", "odometry": "odometry_", "gt": "gt_"}
#: The estimates a folder of each kind holds (ground truth: always).
ESTIMATES = {"slam": ("slam", "odometry"), "odometry": ("odometry",)}

_SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]*$")
#: What a results folder holds (the writers' files, ``radarslam eval``'s, the benchmark's, the
#: temporary files of atomic writes). An existing folder is replaced only when it holds nothing
#: else.
_RESULT_ENTRY = re.compile(
    r"^(?:(?:poses|odometry|gt)_[^/]+\.(?:tum|kitti)|key_frames_[^/]+\.csv|run\.json|config\.yaml"
    r"|loops\.csv|map\.ply|timing\.json|metrics\.json|summary\.json|bench\.json|pose_graph\.g2o"
    r"|plots|\.[^/]*\.tmp[^/]*)$"
)


def check_session_name(name: str) -> str:
    """``name`` when it can be part of a file name; DataError otherwise."""
    if not _SAFE_NAME.match(name or ""):
        raise DataError(
            f"session name {name!r} cannot be used in file names (letters, digits, _ . - only)"
        )
    return name


def trajectory_path(folder: str | Path, kind: str, session: str, suffix: str = ".tum") -> Path:
    """``<folder>/<prefix><session><suffix>`` of trajectory ``kind`` (slam, odometry, gt)."""
    return Path(folder) / f"{TRAJECTORY_PREFIX[kind]}{session}{suffix}"


def key_frames_path(folder: str | Path, session: str) -> Path:
    """The key-frame motions of a session in an odometry folder."""
    return Path(folder) / f"key_frames_{session}.csv"


def check_results_dir(results_dir: str | Path) -> Path:
    """Fail before any work when ``results_dir`` cannot become a results folder: a file is in
    the way, its parent cannot be created or written, or it is a folder holding other things
    (which :func:`write_results_folder` would replace). Creates the parent folder; returns the
    folder to write."""
    return check_output_folder(results_dir, _is_result_entry, "result file")


def _is_result_entry(entry: Path) -> bool:
    # anything else (a user's notes beside the results, say) would be lost with the folder
    return bool(_RESULT_ENTRY.match(entry.name))


def write_trajectories(
    folder: str | Path,
    session: str,
    timestamps_us: np.ndarray,
    trajectories: Mapping[str, np.ndarray | None],
) -> None:
    """``<prefix><session>.tum`` and ``.kitti`` of each trajectory (kind -> (N, 4, 4) poses at
    ``timestamps_us``; ``None``: not written)."""
    check_session_name(session)
    ts = np.asarray(timestamps_us)
    for kind, poses in trajectories.items():
        if poses is None:
            continue
        write_tum(trajectory_path(folder, kind, session), ts, poses)
        write_kitti(trajectory_path(folder, kind, session, ".kitti"), poses)


def write_results_folder(
    results_dir: str | Path,
    sessions: Sequence[str],
    kind: str,
    contents: Callable[[Path], None],
    *,
    method: str | None = None,
    components: Sequence[Sequence[str]] | None = None,
    continues: Mapping[str, str] | None = None,
    extra_json: Mapping[str, object] | None = None,
    finish: Callable[[Path], None] | None = None,
) -> Path:
    """Write a results folder as a whole: ``contents(folder)`` writes the files, then
    ``run.json`` (so that a folder with it is complete), ``extra_json`` (name -> JSON object) and
    ``finish(folder)`` last, all into a hidden sibling that then replaces ``results_dir``
    (:func:`radarslam.io.atomic.atomic_folder`): a reader never sees a partial folder, an
    interrupted run leaves the previous one, a re-run leaves no file of the previous run. An
    existing ``results_dir`` is replaced only when it is a results folder
    (:func:`check_results_dir`)."""
    if kind not in RESULT_KINDS:
        raise ValueError(f"results folder kind {kind!r}: one of {RESULT_KINDS}")
    names = [check_session_name(s) for s in sessions]
    if len(set(names)) != len(names):
        raise DataError(f"results: duplicate session names in {names}")
    target = check_results_dir(results_dir)
    with atomic_folder(target) as tmp:
        contents(tmp)
        run: dict[str, object] = {"format": RESULTS_FORMAT, "kind": kind, "sessions": names}
        if method is not None:
            run["method"] = method
        if components is not None:  # the anchored map first; the others live in their own frames
            run["components"] = [list(c) for c in components]
        if continues:  # session -> the one whose drive it continues: one pass for the metrics
            run["continues"] = dict(continues)
        write_json_atomic(tmp / "run.json", run)
        for name, obj in (extra_json or {}).items():
            write_json_atomic(tmp / name, obj)
        if finish is not None:
            finish(tmp)
    return Path(results_dir)


# --- reading -------------------------------------------------------------------------------------


@dataclass
class ResultsFolder:
    path: Path
    sessions: list[str]  # processing order
    trajectories: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]]  # session -> kind -> (t, T)
    loops_path: Path | None
    #: Map components from run.json (the anchored map first), None when not recorded.
    components: list[list[str]] | None = None
    #: ``slam`` or ``odometry`` (see the module docstring).
    kind: str = "slam"
    #: The odometry method of an odometry folder, when recorded.
    method: str | None = None
    #: session -> the session whose drive it continues (one pass of the vehicle), from run.json.
    continues: dict[str, str] = field(default_factory=dict)


def read_results(results_dir: str | Path) -> ResultsFolder:
    """The sessions ``run.json`` lists, in its order, with their trajectory files.

    ``run.json`` is written last (and the folder as a whole, :func:`write_results_folder`): a
    folder without it is incomplete. Files of sessions it does not list are not read. Every
    listed session needs ``gt_<s>.tum`` and, in a SLAM folder, ``poses_<s>.tum`` (its
    ``odometry_<s>.tum`` is optional: one warning names a missing one), in an odometry folder
    ``odometry_<s>.tum``. Where a ``.tum`` file is missing but its ``.kitti`` twin is there, the
    KITTI poses are read with the timestamps of another TUM file of the session.
    """
    d = Path(results_dir)
    if d.is_file():
        raise DataError(f"{d}: is a file, not a results folder")
    if not d.is_dir():
        raise DataError(f"{d}: results folder does not exist")
    run = d / "run.json"
    if not run.is_file():
        if not any(any(d.glob(f"{prefix}*.tum")) for prefix in TRAJECTORY_PREFIX.values()):
            raise DataError(f"{d}: no poses_*.tum, odometry_*.tum or gt_*.tum files")
        raise DataError(
            f"{d}: no run.json: not a complete results folder (was the run interrupted?)"
        )
    meta = _read_run_json(run)
    sessions = meta.get("sessions")
    if (
        not isinstance(sessions, list)
        or not sessions
        or not all(isinstance(s, str) and s for s in sessions)
    ):
        raise DataError(f"{run}: 'sessions' must be a non-empty list of names")
    if len(set(sessions)) != len(sessions):
        raise DataError(f"{run}: 'sessions' lists a session twice: {sessions}")
    for s in sessions:
        try:
            check_session_name(s)  # names make file names: no path separators
        except DataError as exc:
            raise DataError(f"{run}: {exc}") from None
    kind = meta.get("kind", "slam")
    if kind not in RESULT_KINDS:
        raise DataError(f"{run}: 'kind' must be one of {', '.join(RESULT_KINDS)}, got {kind!r}")
    method = meta.get("method")
    if method is not None and not isinstance(method, str):
        raise DataError(f"{run}: 'method' must be a string, got {method!r}")
    wanted = (*ESTIMATES[kind], "gt")
    optional = "odometry" if kind == "slam" else None
    found: dict[str, dict[str, tuple[np.ndarray, np.ndarray]]] = {}
    no_odometry: list[Path] = []
    for s in sessions:
        found[s] = {}
        kitti_only = []
        for k in wanted:
            p = trajectory_path(d, k, s)
            if p.is_file():
                found[s][k] = read_tum(p)
            elif p.with_suffix(".kitti").is_file():
                kitti_only.append((k, p.with_suffix(".kitti")))
            elif k != optional:
                raise DataError(f"{p}: missing (run.json lists session {s!r})")
            else:
                no_odometry.append(p)
        for k, path in kitti_only:
            found[s][k] = _read_kitti_twin(path, s, found[s])
    if no_odometry:
        log.warning(
            "%s: missing; session %r is evaluated without its odometry (%d of %d session(s) "
            "without)",
            no_odometry[0],
            no_odometry[0].stem.removeprefix(TRAJECTORY_PREFIX["odometry"]),
            len(no_odometry),
            len(sessions),
        )
    return ResultsFolder(
        d,
        sessions,
        found,
        (d / "loops.csv") if kind == "slam" and (d / "loops.csv").is_file() else None,
        _components(run, meta, sessions),
        kind,
        method,
        _continues(run, meta, sessions),
    )


def _read_kitti_twin(
    path: Path, session: str, tum: dict[str, tuple[np.ndarray, np.ndarray]]
) -> tuple[np.ndarray, np.ndarray]:
    """A KITTI trajectory whose TUM twin is missing: the trajectories of a session share their
    timestamps (one pose per key frame or frame), so they are taken from a TUM file of the same
    session with as many poses."""
    poses = read_kitti(path)
    for kind in ("gt", "slam", "odometry"):
        if kind in tum and len(tum[kind][0]) == len(poses):
            return tum[kind][0], poses
    raise DataError(
        f"{path}: KITTI poses carry no timestamps and no TUM file of session {session!r} has "
        f"{len(poses)} poses to take them from"
    )


def _read_run_json(run: Path) -> dict:
    try:
        meta = json.loads(read_text(run, "run.json"))
    except json.JSONDecodeError as exc:
        raise DataError(f"{run}:{exc.lineno}: invalid JSON ({exc.msg})") from None
    if not isinstance(meta, dict):
        raise DataError(f"{run}: not a JSON object with a 'sessions' list")
    fmt = meta.get("format")
    if fmt is not None and fmt != RESULTS_FORMAT:
        raise DataError(
            f"{run}: results format {fmt!r} is not supported (this code reads {RESULTS_FORMAT})"
        )
    return meta


def _continues(run: Path, meta: dict, sessions: list[str]) -> dict[str, str]:
    cont = meta.get("continues", {})
    if not isinstance(cont, dict) or not all(
        isinstance(k, str) and isinstance(v, str) for k, v in cont.items()
    ):
        raise DataError(f"{run}: 'continues' must map session names to session names")
    order = {s: i for i, s in enumerate(sessions)}
    for later, earlier in cont.items():
        if later not in order or earlier not in order:
            raise DataError(
                f"{run}: 'continues' names {later!r} -> {earlier!r}, not both among its sessions"
            )
        if order[earlier] >= order[later]:
            raise DataError(
                f"{run}: 'continues': {later!r} continues {earlier!r}, which is not listed "
                "before it"
            )
    doubled = [v for v in set(cont.values()) if list(cont.values()).count(v) > 1]
    if doubled:
        raise DataError(f"{run}: 'continues': two sessions continue {doubled[0]!r}")
    return dict(cont)


def _components(run: Path, meta: dict, sessions: list[str]) -> list[list[str]] | None:
    comps = meta.get("components")
    if comps is None:
        return None
    if (
        not isinstance(comps, list)
        or not comps
        or not all(
            isinstance(c, list) and c and all(isinstance(s, str) and s in sessions for s in c)
            for c in comps
        )
    ):
        raise DataError(
            f"{run}: 'components' must be a non-empty list of non-empty lists of the sessions "
            "it lists"
        )
    # A session lies in one component at most (the joint ATE aligns each component once; a
    # session without key frames is in none).
    listed = [s for c in comps for s in c]
    twice = sorted({s for s in listed if listed.count(s) > 1})
    if twice:
        raise DataError(f"{run}: 'components' lists {', '.join(twice)} more than once")
    return comps
