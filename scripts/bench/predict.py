"""Inference benchmark: images/s and peak memory of ``model.predict``, beside the paper's figures.

    python scripts/bench/predict.py                          # CPU: both recipes, both modes, 2 images
    python scripts/bench/predict.py --device cuda --images 50
    python scripts/bench/predict.py --config hypersim --size 192 256 --images 1   # a quick smoke run

Recipes at the paper's image sizes (Scene-Shapes 512x512, Hypersim 768x1024) with synthetic
frames (random image, ``--objects`` true boxes; the cost of a forward pass does not depend on
the pixels), one image per call as a user's ``usl-predict`` would run it. ``gt_boxes`` predicts
shape and layout for the true boxes (how the paper evaluates), ``detections`` runs the RPN and box
head first. The paper reports 8 fps (Scene-Shapes) and 3 fps (Hypersim) on a V100; a ratio
against it is printed only for CUDA runs (a CPU is not a V100).
"""

from __future__ import annotations

import argparse
import resource
import statistics
import time

import torch
from train import DEFAULT_OBJECTS, DEFAULT_SIZE  # scripts/bench/train.py, which puts the checkout on sys.path

from tests.data.synthetic_samples import synthetic_config, synthetic_sample  # noqa: E402
from usl.model.usl_model import MODES, USLModel  # noqa: E402

PAPER_FPS = {"scene_shapes": 8.0, "hypersim": 3.0}  # V100, paper Sec. 4


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def bench(config: str, args: argparse.Namespace, device: torch.device) -> list[dict]:
    cfg = synthetic_config(config, args.overrides)
    model = USLModel(cfg.model, cfg.loss).to(device).eval()
    height, width = args.size or DEFAULT_SIZE[config]
    objects = args.objects or DEFAULT_OBJECTS[config]
    frames = [
        synthetic_sample(i, height, width, objects, 1, len(cfg.model.categories)).to(device).frame
        for i in range(args.images)
    ]
    rows = []
    for mode in MODES:
        for frame in frames[: args.warmup]:
            model.predict([frame], mode)
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        times = []
        for frame in frames:
            _sync(device)
            start = time.perf_counter()
            model.predict([frame], mode)
            _sync(device)
            times.append(time.perf_counter() - start)
        peak = (
            torch.cuda.max_memory_allocated(device) / 2**30
            if device.type == "cuda"
            else resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
        )
        rows.append(
            {
                "config": config,
                "mode": mode,
                "size": f"{height}x{width}",
                "fps": 1.0 / statistics.median(times),
                "peak": peak,
            }
        )
    return rows


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--config", nargs="+", default=list(PAPER_FPS), choices=sorted(DEFAULT_SIZE))
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--images", type=int, default=2, help="timed images per mode (default kept short for CPUs)")
    p.add_argument("--warmup", type=int, default=1)
    p.add_argument("--size", type=int, nargs=2, metavar=("H", "W"), help="image size (default: the paper's)")
    p.add_argument("--objects", type=int, help="true boxes per image (default: the recipe's typical count)")
    p.add_argument("--threads", type=int, default=0, help="CPU intra-op threads (0: torch default)")
    p.add_argument("overrides", nargs="*", help="config overrides key=value (e.g. model.init_weights=...)")
    args = p.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    configs = args.config
    rows = [row for config in configs for row in bench(config, args, device)]
    memory = "peak GPU GiB" if device.type == "cuda" else "peak RSS GiB"
    print(f"model.predict, device={device}, 1 image per call, median of {args.images} (after {args.warmup} warm-up)")
    print(f"{'config':>13} {'mode':>11} {'size':>9} {'images/s':>9} {memory:>13} {'paper (V100)':>13} {'vs paper':>9}")
    for row in rows:
        paper = PAPER_FPS.get(row["config"])
        ratio = f"{row['fps'] / paper:8.2f}x" if paper and device.type == "cuda" else f"{'-':>9}"
        paper_text = f"{paper:.0f} fps" if paper else "-"
        print(
            f"{row['config']:>13} {row['mode']:>11} {row['size']:>9} {row['fps']:9.2f} {row['peak']:13.2f} {paper_text:>13} {ratio}"
        )


if __name__ == "__main__":
    main()
