#!/usr/bin/env python
"""AutoPlace model smoke checks that need no dataset: throughput and a (multi-GPU) training run.

    # descriptor throughput of the presets on this machine (CPU threads or CUDA)
    python tools/ddp_smoke.py throughput --presets paper_se_te compact_se_te --threads 2
    # a short training run of a preset on a synthetic 200x200 corridor; under torchrun it is DDP
    torchrun --nproc_per_node=2 tools/ddp_smoke.py train --preset paper_se_te --epochs 2

The synthetic corridor is a long street of random landmarks driven four times (database, train,
val, test drives offset along and across the road, with dropped landmarks and clutter), rendered
as binary occupancy at 1 m/px: enough to exercise mining, the loss, validation, checkpointing and
DDP at the real image size. It is not a benchmark of recognition quality.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def synthetic_corridor(
    n_db: int = 200,
    size: int = 200,
    step_m: float = 2.0,
    landmarks_per_m: float = 4.0,
    seed: int = 0,
):
    """PreparedData of four drives along a corridor of random landmarks (see module doc)."""
    from radarslam.place_recognition.dataset import PreparedData

    rng = np.random.default_rng(seed)
    half = size // 2
    length = (n_db - 1) * step_m
    n_lm = int(landmarks_per_m * (length + size))
    lm = np.column_stack([rng.uniform(-half, length + half, n_lm), rng.uniform(-half, half, n_lm)])
    drives = [("db", 0.0, 0.0, n_db), ("train", 1.0, 0.5, n_db - 1)]
    drives += [("val", 0.5, -0.5, n_db - 1), ("test", 1.5, 1.0, n_db - 1)]
    images, positions, names = [], [], []
    for name, x0, y0, count in drives:
        for k in range(count):
            x = x0 + k * step_m
            rel = lm[np.abs(lm[:, 0] - x) < half + 1] - (x, y0)
            rel = rel[rng.random(len(rel)) < 0.75]
            r = np.round(rel[:, 0]).astype(int) + half
            c = np.round(rel[:, 1]).astype(int) + half
            ok = (r >= 0) & (r < size) & (c >= 0) & (c < size)
            img = np.zeros((size, size), np.uint8)
            img[r[ok], c[ok]] = 1
            n_clutter = size * size // 200
            img[rng.integers(0, size, n_clutter), rng.integers(0, size, n_clutter)] = 1
            images.append(img)
            positions.append((x, y0))
            names.append(name)
    return PreparedData.from_drives(f"synthetic-corridor-{n_db}x{size}px", images, positions, names)


def throughput(args) -> dict:
    """Frames/s of the SE trunk (batch of frames) and descriptors/s over a stream of sequences."""
    import torch

    from radarslam.place_recognition.models import (
        build_model,
        load_model_config,
        multiply_adds_per_frame,
        parameter_count,
    )
    from radarslam.place_recognition.train import compute_descriptors, resolve_device

    if args.threads:
        torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    data = synthetic_corridor(n_db=max(args.frames, 16), size=200)
    results = {}
    for name in args.presets:
        cfg = load_model_config(name)
        torch.manual_seed(0)
        fmt = torch.channels_last if args.channels_last else torch.contiguous_format
        model = build_model(cfg).to(device, memory_format=fmt).eval()
        frames = torch.from_numpy(data.images[: args.batch, None]).float().to(device)
        with torch.no_grad():
            model.encode_frames(frames)  # warm-up (allocator, oneDNN / cuDNN plans)
            if device.type == "cuda":
                torch.cuda.synchronize()
            t0, c0 = time.perf_counter(), time.process_time()
            for _ in range(args.repeats):
                model.encode_frames(frames)
            if device.type == "cuda":
                torch.cuda.synchronize()
            enc = args.batch * args.repeats / (time.perf_counter() - t0)
            # CPU seconds consumed: on a machine shared with other jobs, wall time is inflated by
            # waiting for a core, CPU time much less so.
            enc_cpu = args.batch * args.repeats / max(time.process_time() - c0, 1e-9)
        idx = data.splits["database"][: args.frames]
        compute_descriptors(model, data, idx[:4], batch_size=args.batch, device=device)
        t0 = time.perf_counter()
        compute_descriptors(model, data, idx, batch_size=args.batch, device=device)
        stream = len(idx) / (time.perf_counter() - t0)
        results[name] = {
            "parameters": parameter_count(model),
            "gmac_per_frame": round(multiply_adds_per_frame(cfg) / 1e9, 3),
            "encoder_frames_per_s": round(enc, 2),
            "encoder_frames_per_cpu_s": round(enc_cpu, 2),
            "stream_descriptors_per_s": round(stream, 2),
        }
        print(f"{name:>14}: {json.dumps(results[name])}", flush=True)
        del model
    meta = {"device": str(device), "threads": torch.get_num_threads(), "batch": args.batch,
            "channels_last": args.channels_last}  # fmt: skip
    return {"meta": meta, "presets": results}


def smoke_train(args) -> dict:
    import torch

    from radarslam.place_recognition.models import load_model_config
    from radarslam.place_recognition.train import TrainConfig, train

    rank = int(os.environ.get("RANK", "0"))
    data = synthetic_corridor(n_db=args.frames, size=200)
    model_cfg = load_model_config(args.preset)
    train_cfg = TrainConfig(
        epochs=args.epochs,
        select_after_epoch=0,
        patience=0,
        device=args.device,
        queries_per_epoch=args.queries,
        micro_batch_size=args.micro_batch,
        cache_batch_size=args.cache_batch,
        deterministic=False,
        amp_bf16=args.amp,
    )
    t0 = time.perf_counter()
    result = train(train_cfg, model_cfg, data, args.out, progress=rank == 0 and args.progress)
    out = {
        "rank": rank,
        "world_size": int(os.environ.get("WORLD_SIZE", "1")),
        "device": args.device,
        "cuda": torch.cuda.is_available(),
        "preset": args.preset,
        "amp_bf16": args.amp,
        "seconds": round(time.perf_counter() - t0, 1),
        "best_epoch": result.best_epoch,
        "best_recall_at_1": result.best_recall_at_1,
        "history": result.history,
    }
    if rank == 0:
        print(json.dumps(out, indent=1), flush=True)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("throughput", help="frames/s of the model presets")
    p.add_argument("--presets", nargs="+", default=["paper_se_te", "compact_se_te"])
    p.add_argument("--threads", type=int, default=None)
    p.add_argument("--device", default="cpu")
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--frames", type=int, default=24, help="sequences in the stream measurement")
    p.add_argument("--channels-last", action="store_true", help="NHWC convolution weights")
    p.add_argument("--json", type=Path, default=None)
    t = sub.add_parser("train", help="short training run on a synthetic corridor (DDP-aware)")
    t.add_argument("--preset", default="compact_se_te")
    t.add_argument("--epochs", type=int, default=2)
    t.add_argument("--frames", type=int, default=120, help="database frames of the corridor")
    t.add_argument("--queries", type=int, default=None, help="train queries per epoch")
    t.add_argument("--micro-batch", type=int, default=None)
    t.add_argument("--cache-batch", type=int, default=32)
    t.add_argument("--device", default="auto")
    t.add_argument("--out", type=Path, default=Path("/tmp/autoplace_smoke"))
    t.add_argument("--amp", action="store_true", help="bfloat16 autocast (CUDA)")
    t.add_argument("--progress", action="store_true")
    t.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    result = throughput(args) if args.cmd == "throughput" else smoke_train(args)
    if args.json and int(os.environ.get("RANK", "0")) == 0:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
