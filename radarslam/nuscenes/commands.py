"""CLI commands of the nuScenes stage (light at import time: the reader is imported on call)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

# Every command that reads a dataroot takes --version and --scenes in this one form, with this
# default (tests/test_cli_consistency.py checks them all).
VERSION_DEFAULT = "v1.0-mini"
VERSION_HELP = "v1.0-mini, v1.0-trainval or v1.0-test."
SCENES_HELP = "Comma-separated scene names (default: all)."


def scene_names(text: str | None, option: str = "--scenes") -> list[str] | None:
    """The names of a comma-separated ``--scenes`` value; ``None`` when the option was not given.

    An empty name (``--scenes ""``, ``a,,b``, a trailing comma) is a :class:`ConfigError`: the
    option left out means all scenes, an empty value is a mistake, not a request for them."""
    from radarslam.errors import ConfigError

    if text is None:
        return None
    names = [s.strip() for s in text.split(",")]
    if not all(names):
        raise ConfigError(
            f"{option} {text!r}: empty scene name; give comma-separated scene names, or leave "
            f"{option} out for all scenes"
        )
    return names


def check_output_names(reader, infos) -> None:
    """The scenes' names make the file names of a results folder: a name that cannot (a damaged
    scene.json) fails before the run, naming the table, not when the results are written."""
    from radarslam.errors import DataError
    from radarslam.io.results import check_session_name

    for info in infos:
        try:
            check_session_name(info.name)
        except DataError as exc:
            raise DataError(f"{reader.tables.path('scene')}: {exc}") from None


def stats(
    dataroot: Annotated[Path, typer.Argument(help="nuScenes dataroot (holds <version>/*.json).")],
    version: Annotated[str, typer.Option(help=VERSION_HELP)] = VERSION_DEFAULT,
    reference: Annotated[
        Path | None,
        typer.Option(help="Reference dataroot (e.g. real nuScenes) measured the same way."),
    ] = None,
    reference_version: Annotated[
        str | None, typer.Option(help="The reference's version (default: --version).")
    ] = None,
    scenes: Annotated[str | None, typer.Option(help=SCENES_HELP)] = None,
    reference_scenes: Annotated[
        str | None,
        typer.Option(help="Comma-separated scene names of the reference (default: all)."),
    ] = None,
    max_sweeps: Annotated[
        int | None,
        typer.Option(
            help="Read the first N frames of each scene only (one sweep per radar each).", min=1
        ),
    ] = None,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Also write the figures to this JSON file.")
    ] = None,
) -> None:
    """Radar statistics of a dataroot; with --reference, beside the same figures of a reference
    dataroot and their ratio."""
    from radarslam.errors import ConfigError
    from radarslam.io.atomic import write_json_atomic
    from radarslam.nuscenes.reader import NuScenesRadar
    from radarslam.nuscenes.stats import dataset_statistics

    if reference is None:
        for name, value in (
            ("--reference-version", reference_version),
            ("--reference-scenes", reference_scenes),
        ):
            if value is not None:
                raise ConfigError(f"{name} {value!r}: given without --reference")
    if json_out is not None and json_out.is_dir():
        raise ConfigError(f"--json {json_out}: is a folder, not a file")
    # both dataroots and every scene name are checked before the long part starts
    names = scene_names(scenes)
    reader = NuScenesRadar(dataroot, version)
    for name in names or []:
        reader.scene(name)
    ref_reader = ref_names = None
    if reference is not None:
        ref_names = scene_names(reference_scenes, "--reference-scenes")
        ref_reader = NuScenesRadar(reference, reference_version or version)
        for name in ref_names or []:
            ref_reader.scene(name)
    st = dataset_statistics(reader, names, max_sweeps, desc=f"stats {dataroot.name}")
    ref = None
    if ref_reader is not None and reference is not None:
        ref = dataset_statistics(ref_reader, ref_names, max_sweeps, desc=f"stats {reference.name}")
    table = comparison(st.to_dict(), None if ref is None else ref.to_dict())
    typer.echo(comparison_markdown(table, st, ref))
    if json_out is not None:
        write_json_atomic(
            json_out,
            {
                "dataroot": st.to_dict(),
                "reference": None if ref is None else ref.to_dict(),
                "comparison": table,
            },
        )
        typer.echo(f"wrote {json_out}")


#: Radar channels in RADAR_CHANNELS order, abbreviated for the per-radar rows.
_SHORT = ("F", "FL", "FR", "BL", "BR")

#: (key, label, path in DatasetStats.to_dict(), kind): kind "1" / "3" a number shown with one /
#: three decimals, "%" a fraction shown in percent, "dB" a level (one decimal) whose ratio means
#: nothing: the difference is shown instead.
_ROWS: tuple[tuple[str, str, str, str], ...] = (
    ("raw_mean", "points per sweep before filtering, mean", "counts.raw_mean", "1"),
    ("mean", "points per sweep after filters, mean", "counts.mean", "1"),
    ("p10", "points per sweep after filters, p10", "counts.p10", "1"),
    ("p50", "points per sweep after filters, p50", "counts.p50", "1"),
    ("p90", "points per sweep after filters, p90", "counts.p90", "1"),
    ("empty", "empty sweeps (after filters)", "counts.empty_fraction", "%"),
    ("redetect_next", "static point re-detected within 1 m, next sweep", "redetection.next", "3"),
    ("redetect_3", "... within the next 3 sweeps", "redetection.within", "3"),
    (
        "heading_worst",
        "Doppler heading error, worst scene (deg/s)",
        "doppler.heading_error_worst_dps",
        "3",
    ),
    (
        "heading_median",
        "Doppler heading error, median scene (deg/s)",
        "doppler.heading_error_median_dps",
        "3",
    ),
    ("speed_scale", "Doppler speed scale (fit path / true path)", "doppler.speed_scale", "3"),
    ("range_p10", "range p10 (m)", "points.range_m.p10", "1"),
    ("range_p50", "range p50 (m)", "points.range_m.p50", "1"),
    ("range_p90", "range p90 (m)", "points.range_m.p90", "1"),
    ("rcs_p10", "RCS p10 (dBsm)", "points.rcs_dbsm.p10", "dB"),
    ("rcs_p50", "RCS p50 (dBsm)", "points.rcs_dbsm.p50", "dB"),
    ("rcs_p90", "RCS p90 (dBsm)", "points.rcs_dbsm.p90", "dB"),
    ("moving", "points the Doppler fit marks moving", "points.moving_fraction", "%"),
    (
        "doppler_residual_p50",
        "Doppler residual against the frame's fit, p50 (m/s)",
        "points.doppler_residual_mps.p50",
        "3",
    ),
    (
        "doppler_residual_p75",
        "Doppler residual against the frame's fit, p75 (m/s)",
        "points.doppler_residual_mps.p75",
        "3",
    ),
)

#: Per-radar rows: (key, label, path of a {channel: value} dict, kind).
_RADAR_ROWS: tuple[tuple[str, str, str, str], ...] = (
    ("radar_mean", "points per sweep after filters, mean", "counts.per_radar_mean", "1"),
    (
        "radar_redetect_next",
        "re-detected within 1 m, next sweep",
        "redetection.per_radar_next",
        "3",
    ),
    ("radar_redetect_3", "... within the next 3 sweeps", "redetection.per_radar_within", "3"),
    ("radar_range_p50", "range p50 (m)", "points.per_radar_range_p50_m", "1"),
    ("radar_range_p90", "range p90 (m)", "points.per_radar_range_p90_m", "1"),
    ("radar_rcs_p50", "RCS p50 (dBsm)", "points.per_radar_rcs_p50_dbsm", "dB"),
    (
        "radar_moving",
        "points the Doppler fit marks moving",
        "points.per_radar_moving_fraction",
        "%",
    ),
)


def _get(d: dict, path: str):
    for part in path.split("."):
        d = d[part]
    return d


def _ratio(value, ref, kind: str) -> float | None:
    """value / ref (for a level in dB: value - ref); None where it is undefined."""
    if value is None or ref is None:
        return None
    if kind == "dB":
        return value - ref
    if value == ref:
        return 1.0
    return value / ref if ref != 0 else None


def comparison(st: dict, ref: dict | None) -> list[dict]:
    """One row per figure: key, label, value, reference, ratio (None without a reference)."""
    from radarslam.types import RADAR_CHANNELS

    rows = []
    for key, label, path, kind in _ROWS:
        v = _get(st, path)
        r = None if ref is None else _get(ref, path)
        rows.append(
            {"key": key, "label": label, "kind": kind, "value": v, "reference": r,
             "ratio": _ratio(v, r, kind)}
        )  # fmt: skip
    for key, label, path, kind in _RADAR_ROWS:
        for ch, short in zip(RADAR_CHANNELS, _SHORT, strict=True):
            v = _get(st, path).get(ch)
            r = None if ref is None else _get(ref, path).get(ch)
            rows.append(
                {"key": f"{key}.{ch}", "label": f"{label} ({short})", "kind": kind, "value": v,
                 "reference": r, "ratio": _ratio(v, r, kind)}
            )  # fmt: skip
    return rows


def _fmt(x, kind: str) -> str:
    if x is None:
        return "n/a"
    if kind == "%":
        return f"{100 * x:.2f} %"
    return f"{x:.3f}" if kind == "3" else f"{x:.1f}"


def _fmt_ratio(x, kind: str) -> str:
    if x is None:
        return "n/a"
    return f"{x:+.1f} dB" if kind == "dB" else f"{x:.2f}"


def comparison_markdown(rows: list[dict], st, ref) -> str:
    """The figures as a Markdown table; per-radar figures compacted to one row each, the five
    radars' values separated by slashes (F / FL / FR / BL / BR)."""
    from radarslam.nuscenes.stats import filter_text, odometry_inputs

    def about(s) -> str:
        return (
            f"{s.dataroot} ({s.version}): {s.num_scenes} scenes, {s.num_frames} frames, "
            f"{s.counts.num_sweeps} sweeps"
        )

    lines = [f"Radar statistics of {about(st)}"]
    if ref is not None:
        lines.append(f"reference: {about(ref)}")
    lines.append(
        f"(filtered: {filter_text(odometry_inputs()[0])}; static and moving: the odometry's joint "
        "Doppler fit)"
    )
    lines.append("")
    if ref is None:
        lines += ["| statistic | value |", "|---|---|"]
    else:
        lines += [
            "| statistic | dataroot | reference | ratio (dataroot / reference) |",
            "|---|---|---|---|",
        ]
    n_main = len(_ROWS)
    table = rows[:n_main]
    for k in range(len(_RADAR_ROWS)):  # the five channels of one figure as one row
        group = rows[n_main + 5 * k : n_main + 5 * (k + 1)]
        label = f"per radar {'/'.join(_SHORT)}: {_RADAR_ROWS[k][1]}"
        table.append({"label": label, "kind": group[0]["kind"], "group": group})
    for row in table:
        group = row.get("group", [row])
        kind = row["kind"]
        value = " / ".join(_fmt(g["value"], kind) for g in group)
        if ref is None:
            lines.append(f"| {row['label']} | {value} |")
            continue
        refv = " / ".join(_fmt(g["reference"], kind) for g in group)
        ratio = " / ".join(_fmt_ratio(g["ratio"], kind) for g in group)
        lines.append(f"| {row['label']} | {value} | {refv} | {ratio} |")
    return "\n".join(lines) + "\n"
