"""AutoPlace place-recognition benchmark on the synthetic city (held-out days).

One table: the paper's ablation rows (SE, SE+TE, SE+DPR, SE+TE+DPR, each with/without RCSHR, RCSHR
tuned on val) for the compact preset (trained here unless checkpoints are given) and, when
``--checkpoint-dir`` holds them, the paper-size model; the handcrafted baselines (ScanContext,
M2DP on the same DPR'd points); descriptor throughput on 2 CPU threads and parameter counts.

    python bench/place_recognition.py --dataroot /tmp/city --out outputs/bench/pr
    python bench/place_recognition.py --dataroot /tmp/city --checkpoint-dir ckpts/  # GPU-trained

Checkpoints in ``--checkpoint-dir`` are named ``<size>_<slug>.pt`` (size compact|paper, slug
se|se_te|se_dpr|se_te_dpr), or ``<size>/<slug>.pt``, or ``<size>_<slug>/best.pt`` (train output).
Targets (printed as PASS/FAIL): full AutoPlace R@1 >= SE R@1 + 3 and >= best handcrafted + 20;
compact within 2 R@1 points of the paper-size model at >= 5x its CPU throughput.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def throughput(preset: str, threads: int = 2, frames: int = 48, batch: int = 16) -> dict:
    """Descriptors/s of an (untrained) network on CPU: every sequence encodes seq_len frames."""
    import torch

    from radarslam.place_recognition.models import build_model, load_model_config, parameter_count

    cfg = load_model_config(preset)
    model = build_model(cfg).eval()
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        rng = np.random.default_rng(0)
        shape = (batch, cfg.seq_len, cfg.in_channels, cfg.image_size_px, cfg.image_size_px)
        x = torch.from_numpy((rng.random(shape) < 0.03).astype(np.float32))
        with torch.no_grad():
            model(x[:2])  # warm-up
            t0 = time.perf_counter()
            n = 0
            while n < frames:
                model(x)
                n += batch
            dt = time.perf_counter() - t0
    finally:
        torch.set_num_threads(before)
    # independent sequences: each descriptor encodes seq_len frames (no frame sharing)
    return {
        "preset": preset,
        "params": parameter_count(model),
        "descriptors_per_s": n / dt,
        "frames_per_s": n * cfg.seq_len / dt,
        "threads": threads,
    }


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dataroot", type=Path, required=True, help="synthetic city dataroot")
    ap.add_argument("--config", type=Path, default=None, help="data YAML (default data_city)")
    ap.add_argument("--cache-root", type=Path, default=Path("outputs/place_recognition"))
    ap.add_argument("--out", type=Path, default=Path("outputs/bench/place_recognition"))
    ap.add_argument("--checkpoint-dir", type=Path, default=None)
    ap.add_argument("--train-preset", default="compact_cpu")
    ap.add_argument("--train-set", action="append", default=[], help="train override k=v")
    ap.add_argument("--no-train", action="store_true", help="only use given checkpoints")
    ap.add_argument(
        "--te-init-from-se",
        action="store_true",
        help="two-stage training: TE variants start from the trained SE variant's encoder",
    )
    ap.add_argument("--device", default="cpu", help="descriptor device")
    ap.add_argument("--sizes", default="compact,paper", help="model sizes to evaluate")
    ap.add_argument("--threads", type=int, default=2, help="CPU threads for throughput")
    ap.add_argument("--jobs", type=int, default=1, help="processes for preprocessing")
    ap.add_argument(
        "--parts",
        default="baselines,models,speed",
        help="what to run: baselines, models, speed (comma-separated)",
    )
    ap.add_argument(
        "--include",
        type=Path,
        action="append",
        default=[],
        help="rows of an earlier run's place_recognition.json to add to the table",
    )
    args = ap.parse_args(argv)
    parts = set(args.parts.split(","))

    from radarslam.config import CONFIG_DIR, load_config
    from radarslam.io.atomic import write_text_atomic
    from radarslam.place_recognition.ablation import (
        VARIANTS,
        find_checkpoint,
        prepare_pair,
        run_ablation,
    )
    from radarslam.place_recognition.config import EvalConfig, PrepareConfig
    from radarslam.place_recognition.dataset import load_prepared
    from radarslam.place_recognition.evaluate import (
        baseline_ranking_fn,
        evaluate_method,
        markdown_table,
        write_results,
    )

    cfg_path = args.config or CONFIG_DIR / "place_recognition" / "data_city.yaml"
    prep = load_config(PrepareConfig, cfg_path, [f"source.dataroot={args.dataroot}"])
    t0 = time.perf_counter()
    dpr_root, nodpr_root = prepare_pair(prep, args.cache_root, jobs=args.jobs)
    data, data_nodpr = load_prepared(dpr_root), load_prepared(nodpr_root)
    t_prep = time.perf_counter() - t0
    counts = json.loads((dpr_root / "split.json").read_text())
    print(f"prepared {dpr_root} and {nodpr_root} ({t_prep:.0f} s): {counts}")
    eval_cfg = EvalConfig()
    all_results = []
    rows = []

    for name in ("scancontext", "m2dp") if "baselines" in parts else ():
        t = time.perf_counter()
        label, fn = baseline_ranking_fn(data, name, eval_cfg)
        res = evaluate_method(data, label, fn, eval_cfg, "test")
        all_results += res
        row = res[0].row()
        row["s"] = round(time.perf_counter() - t, 1)
        rows.append(row)
        print(markdown_table([row]))

    sizes = [s for s in args.sizes.split(",") if s] if "models" in parts else []
    runs_by_size = {}
    for size in sizes:
        have_any = any(
            find_checkpoint(args.checkpoint_dir, size, s)
            for s in ("se", "se_te", "se_dpr", "se_te_dpr")
        )
        if size != "compact" and not have_any:
            print(f"({size}: no checkpoints in {args.checkpoint_dir}; skipped)")
            continue
        train_preset = args.train_preset if size == "compact" else "paper"
        # only the compact preset is trained here (the paper-size model needs a GPU)
        can_train = size == "compact" and not args.no_train
        variants = tuple(
            v for v in VARIANTS if can_train or find_checkpoint(args.checkpoint_dir, size, v.slug)
        )

        def show(run, size=size):
            for r in run.results:
                row = r.row()
                row.update(method=f"{size} {r.name}", params=run.parameters)
                print(markdown_table([row]), end="")

        runs = run_ablation(
            data, data_nodpr, args.out / "train", size=size, train_preset=train_preset,
            eval_cfg=eval_cfg, checkpoint_dir=args.checkpoint_dir,
            train_overrides=args.train_set, allow_train=can_train, variants=variants,
            device=args.device, on_variant=show, te_init_from_se=args.te_init_from_se and can_train,
        )  # fmt: skip
        runs_by_size[size] = runs
        for run in runs:
            for r in run.results:
                r.name = f"{size} {r.name}"
                all_results.append(r)
                row = r.row()
                row["params"] = run.parameters
                row["checkpoint"] = str(run.checkpoint)
                rows.append(row)

    for inc in args.include:
        rows += json.loads(inc.read_text())["rows"]
    speed = (
        []
        if "speed" not in parts
        else [
            throughput(f"{s}_se_te", args.threads, frames=n)
            for s, n in (("compact", 96), ("paper", 32))
        ]
    )
    speed += (
        []
        if "speed" not in parts
        else [
            throughput(f"{s}_se", args.threads, frames=n)
            for s, n in (("compact", 96), ("paper", 32))
        ]
    )

    # targets
    def r1(name):
        for row in rows:
            if row["method"] == name:
                return float(row["R@1"])
        return None

    checks = []
    best_hand = max(r1("ScanContext") or 0, r1("M2DP") or 0)
    for size in ("compact", "paper"):
        full, se = r1(f"{size} SE+TE+DPR+RCSHR"), r1(f"{size} SE")
        if full is not None and se is not None:
            checks.append((f"{size}: full R@1 {full:.1f} >= SE {se:.1f} + 3", full >= se + 3))
            checks.append((f"{size}: full R@1 {full:.1f} >= best handcrafted {best_hand:.1f} + 20",
                           full >= best_hand + 20))  # fmt: skip
    cp, pp = r1("compact SE+TE+DPR+RCSHR"), r1("paper SE+TE+DPR+RCSHR")
    if cp is not None and pp is not None:
        checks.append((f"compact R@1 {cp:.1f} within 2 of paper {pp:.1f}", cp >= pp - 2))
    if speed:
        ratio = speed[0]["descriptors_per_s"] / speed[1]["descriptors_per_s"]
        checks.append((f"compact SE+TE throughput {ratio:.1f}x paper SE+TE (>= 5x)", ratio >= 5))

    args.out.mkdir(parents=True, exist_ok=True)
    paths = write_results(all_results, args.out, stem="place_recognition")
    # rows (with run details) replace the plain result rows in the JSON
    payload = json.loads(paths["json"].read_text())
    payload["rows"] = rows
    write_text_atomic(paths["json"], json.dumps(payload, indent=2))
    table = markdown_table(rows)
    speed_table = markdown_table(
        [{k: (round(v, 1) if isinstance(v, float) else v) for k, v in s.items()} for s in speed]
    )
    check_lines = "\n".join(f"- [{'PASS' if ok else 'FAIL'}] {text}" for text, ok in checks)
    report = (
        f"# Place recognition on {args.dataroot} (test split, {counts['test']} queries, "
        f"DB {counts['database']})\n\n{table}\n## Descriptor throughput (CPU, {args.threads} "
        f"threads)\n\n{speed_table}\n## Targets\n\n{check_lines}\n"
    )
    write_text_atomic(args.out / "report.md", report)
    write_text_atomic(args.out / "speed.json", json.dumps(speed, indent=2))
    print(report)
    print(f"wrote {args.out / 'report.md'}, {paths['md']}, {paths['png']}")
    return 0


if __name__ == "__main__":
    from _cli import guarded

    guarded(main)
