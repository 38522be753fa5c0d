"""``radarslam pr ...``: prepare, train, eval, build-db, query (light imports at module level)."""

from __future__ import annotations

from pathlib import Path

import typer

from radarslam.nuscenes.commands import SCENES_HELP, VERSION_DEFAULT, VERSION_HELP

pr_app = typer.Typer(
    help="AutoPlace radar place recognition: data, training, evaluation, loop-detector database.",
    no_args_is_help=True,
)

_SET = typer.Option(None, "--set", help="config override key.sub=value (repeatable)")
EVAL_SPLITS = ("val", "test")  # the database and train splits are not held out


def _echo_table(rows: list[dict]) -> None:
    from radarslam.place_recognition.evaluate import markdown_table

    typer.echo(markdown_table(rows))


@pr_app.command("prepare")
def prepare_cmd(
    config: Path = typer.Argument(
        ..., help="prepare YAML (radarslam/configs/place_recognition/data_*.yaml)"
    ),
    out: Path = typer.Option(Path("outputs/place_recognition"), help="cache root"),
    dataroot: Path | None = typer.Option(None, help="nuScenes-layout dataroot (overrides config)"),
    overwrite: bool = typer.Option(False, help="recompute every stage"),
    jobs: int = typer.Option(1, help="worker processes for accumulation"),
    overrides: list[str] | None = _SET,
) -> None:
    """Index key frames, accumulate + DPR + rasterise, split; cached in OUT/<name>/."""
    from radarslam.errors import ConfigError
    from radarslam.place_recognition.config import load_prepare_config
    from radarslam.place_recognition.dataset import split_summary
    from radarslam.place_recognition.outputs import check_output_dir
    from radarslam.place_recognition.prepare import prepare

    if jobs < 1:
        raise ConfigError(f"--jobs {jobs}: must be >= 1")
    check_output_dir(out)
    sets = list(overrides or [])
    if dataroot is not None:
        sets.append(f"source.dataroot={dataroot}")
    cfg = load_prepare_config(config, sets)
    root = prepare(cfg, out, overwrite=overwrite, jobs=jobs)
    typer.echo(f"prepared {root}")
    _echo_table([split_summary(root)])


@pr_app.command("train")
def train_cmd(
    prepared: Path = typer.Argument(..., help="prepared cache directory"),
    model: str = typer.Option("compact_se_te", help="model preset name or YAML"),
    train: str = typer.Option("compact_cpu", help="train preset name or YAML"),
    out: Path = typer.Option(Path("outputs/place_recognition/train"), help="output directory"),
    set_model: list[str] | None = typer.Option(None, "--set-model", help="model override"),
    set_train: list[str] | None = typer.Option(None, "--set-train", help="train override"),
    resume: bool = typer.Option(False, help="continue the run in OUT (OUT/last.pt)"),
    overwrite: bool = typer.Option(False, help="replace a previous run's checkpoints in OUT"),
) -> None:
    """Train an AutoPlace network on a prepared cache (radarslam.place_recognition.train).

    OUT must not hold another run's checkpoints unless --resume or --overwrite is given.
    """
    from radarslam.errors import CheckpointError, ConfigError
    from radarslam.place_recognition.dataset import load_prepared
    from radarslam.place_recognition.models import load_model_config
    from radarslam.place_recognition.outputs import check_output_dir
    from radarslam.place_recognition.train import load_train_config
    from radarslam.place_recognition.train import train as run_train

    check_output_dir(out)
    if resume and overwrite:
        raise ConfigError("give --resume or --overwrite, not both")
    previous = [n for n in ("best.pt", "last.pt") if (out / n).is_file()]
    if resume and not (out / "last.pt").is_file():
        raise CheckpointError(f"{out / 'last.pt'}: nothing to resume (file does not exist)")
    if previous and not (resume or overwrite):
        raise ConfigError(
            f"{out}: holds a previous run ({', '.join(previous)}); pass --resume to continue "
            "it, --overwrite to replace it, or choose another --out"
        )
    model_cfg = load_model_config(model, set_model)
    train_cfg = load_train_config(train, set_train)
    data = load_prepared(prepared)
    result = run_train(train_cfg, model_cfg, data, out, resume=resume)
    typer.echo(f"best checkpoint: {result.best_checkpoint}")


@pr_app.command("eval")
def eval_cmd(
    prepared: Path = typer.Argument(..., help="prepared cache directory"),
    checkpoint: Path | None = typer.Option(None, help="model checkpoint (.pt)"),
    baseline: str | None = typer.Option(None, help="handcrafted baseline: scancontext | m2dp"),
    split: str = typer.Option("test", help="split to evaluate (val or test)"),
    rerank: bool = typer.Option(True, help="also evaluate with RCSHR re-ranking"),
    tune: bool = typer.Option(False, help="grid-search RCSHR parameters on the val split first"),
    config: Path | None = typer.Option(
        None, help="eval YAML (radarslam/configs/place_recognition/eval_*)"
    ),
    out: Path = typer.Option(Path("outputs/place_recognition/eval"), help="output directory"),
    overrides: list[str] | None = _SET,
) -> None:
    """Recall@N, max F1, AP and PR curve on a split; Markdown + JSON + PNG in OUT."""
    from radarslam.errors import ConfigError
    from radarslam.place_recognition.config import load_eval_config
    from radarslam.place_recognition.dataset import load_prepared
    from radarslam.place_recognition.evaluate import (
        baseline_ranking_fn,
        checkpoint_ranking_fn,
        evaluate_method,
        evaluate_turned,
        write_results,
    )
    from radarslam.place_recognition.outputs import check_output_dir

    if (checkpoint is None) == (baseline is None):
        raise ConfigError("give exactly one of --checkpoint or --baseline")
    if split not in EVAL_SPLITS:
        raise ConfigError(f"--split {split!r}: choose one of {', '.join(EVAL_SPLITS)}")
    check_output_dir(out)
    cfg = load_eval_config(config, overrides)
    data = load_prepared(prepared)
    turned_fn = None
    if checkpoint is not None:
        name, fn, turned_fn = checkpoint_ranking_fn(data, checkpoint, cfg)
    else:
        assert baseline is not None  # exactly one of the two was checked above
        name, fn = baseline_ranking_fn(data, baseline, cfg)
    results = evaluate_method(
        data, name, fn, cfg, split, rerank_cfg=cfg.rerank if rerank else None, tune_on_val=tune
    )
    if turned_fn is not None:  # SLAM's turned search, for a street driven the other way round
        turned = evaluate_turned(data, name, turned_fn, cfg, split)
        results += [turned] if turned is not None else []
    paths = write_results(results, out, stem=f"{name}_{split}".replace("+", "_"))
    _echo_table([r.row() for r in results])
    typer.echo(f"wrote {paths['md']}")


@pr_app.command("build-db")
def build_db_cmd(
    dataroot: Path = typer.Option(..., help="nuScenes-layout dataroot"),
    out: Path = typer.Option(..., help="database file (.npz)"),
    version: str = typer.Option(VERSION_DEFAULT, help=VERSION_HELP),
    scenes: str | None = typer.Option(None, help=SCENES_HELP),
    location: str | None = typer.Option(None, help="Every scene of this location."),
    checkpoint: Path | None = typer.Option(None, help="checkpoint (default: shipped compact)"),
    config: Path | None = typer.Option(None, help="recognizer YAML"),
    overrides: list[str] | None = _SET,
) -> None:
    """Describe every key frame of the chosen scenes and save a loop-detector database."""
    from tqdm import tqdm

    from radarslam.config import load_config
    from radarslam.errors import ConfigError
    from radarslam.nuscenes.commands import scene_names
    from radarslam.nuscenes.reader import NuScenesRadar
    from radarslam.place_recognition.config import PlaceRecognizerConfig
    from radarslam.place_recognition.outputs import check_output_file
    from radarslam.place_recognition.recognizer import PlaceRecognizer, iter_scene_sequences

    names = scene_names(scenes)
    if names is not None and location is not None:
        raise ConfigError(f"--scenes {scenes!r} and --location {location!r}: give one or the other")
    check_output_file(out)
    cfg = load_config(PlaceRecognizerConfig, config, overrides)
    rec = PlaceRecognizer(checkpoint=checkpoint, config=cfg)
    reader = NuScenesRadar(dataroot, version)
    if names is not None:
        chosen = [reader.scene(n) for n in names]  # every name checked before the long part
    elif location is not None:
        chosen = reader.scenes_for_location(location)
    else:
        chosen = reader.scenes()
    for info in tqdm(chosen, desc="build-db", unit="scene"):
        for token, clouds in iter_scene_sequences(rec, reader, info):
            rec.add(clouds, key=token)
    rec.save(out)
    typer.echo(f"{len(rec)} places -> {out}")


@pr_app.command("query")
def query_cmd(
    database: Path = typer.Argument(..., help="database from build-db"),
    dataroot: Path = typer.Option(..., help="nuScenes-layout dataroot"),
    scenes: str | None = typer.Option(None, help=SCENES_HELP),
    version: str = typer.Option(VERSION_DEFAULT, help=VERSION_HELP),
    sample_token: str | None = typer.Option(None, help="only this key frame"),
    k: int = typer.Option(5, "-k", "--top-k", help="candidates per query"),
    checkpoint: Path | None = typer.Option(None, help="checkpoint (default: the database's)"),
) -> None:
    """Top-k places for the key frames of the chosen scenes (the database is not modified)."""
    from radarslam.errors import ConfigError, DataError
    from radarslam.nuscenes.commands import scene_names
    from radarslam.nuscenes.reader import NuScenesRadar
    from radarslam.place_recognition.recognizer import PlaceRecognizer, iter_scene_sequences

    if k < 1:
        raise ConfigError(f"-k {k}: must be >= 1")
    names = scene_names(scenes)
    rec = PlaceRecognizer.load(database, checkpoint=checkpoint)
    if len(rec) == 0:
        raise DataError(f"{database}: the database holds no places; nothing to query against")
    reader = NuScenesRadar(dataroot, version)
    chosen = [reader.scene(n) for n in names] if names is not None else reader.scenes()
    found = False
    for info in chosen:
        for token, clouds in iter_scene_sequences(rec, reader, info):
            if sample_token is not None and token != sample_token:
                continue
            found = True
            cands = rec.query(clouds, k=k)
            text = ", ".join(
                f"{c.key} (d={c.descriptor_distance:.3f}, s={c.score:.3f})" for c in cands
            )
            typer.echo(f"{token}: {text}")
    if sample_token is not None and not found:
        where = f"scenes {scenes!r}" if scenes is not None else str(dataroot)
        raise DataError(f"sample {sample_token!r} is not a key frame of {where}")


@pr_app.command("ablation")
def ablation_cmd(
    config: Path = typer.Argument(
        ..., help="prepare YAML (radarslam/configs/place_recognition/data_*.yaml)"
    ),
    dataroot: Path | None = typer.Option(None, help="nuScenes-layout dataroot (overrides config)"),
    cache_root: Path = typer.Option(Path("outputs/place_recognition"), help="cache root"),
    out: Path = typer.Option(Path("outputs/place_recognition/ablation"), help="output directory"),
    size: str = typer.Option("compact", help="model size: compact | paper"),
    train: str = typer.Option("compact_cpu", help="train preset for variants without checkpoint"),
    checkpoint_dir: Path | None = typer.Option(None, help="<size>_<slug>.pt checkpoints"),
    no_train: bool = typer.Option(False, help="fail instead of training a missing variant"),
    device: str = typer.Option("cpu", help="descriptor device"),
) -> None:
    """Table II: SE, SE+TE, SE+DPR, SE+TE+DPR with/without RCSHR (tuned on val) on test."""
    from radarslam.place_recognition.ablation import load_pair, run_ablation, table_ii_rows
    from radarslam.place_recognition.config import load_prepare_config
    from radarslam.place_recognition.evaluate import write_results

    cfg = load_prepare_config(config, [f"source.dataroot={dataroot}"] if dataroot else None)
    data, data_nodpr = load_pair(cfg, cache_root)
    runs = run_ablation(
        data,
        data_nodpr,
        out / "train",
        size=size,
        train_preset=train,
        checkpoint_dir=checkpoint_dir,
        allow_train=not no_train,
        device=device,
    )
    rows = table_ii_rows(runs)
    write_results([r for run in runs for r in run.results], out, stem=f"ablation_{size}")
    _echo_table(rows)
