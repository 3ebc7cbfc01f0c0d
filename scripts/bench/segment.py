"""usl-segment's segmenter on ScanNet-sized frames: frames/s with 1 thread and with every core, side by side.

    python scripts/bench/segment.py                                   # random PointRend weights, CPU
    python scripts/bench/segment.py --weights model_final_edd263.pkl --frames 8
    python scripts/bench/segment.py --device cuda --threads 1        # the CUDA line of scripts/gpu_check.sh

Frames are synthetic 640 x 480 pictures (ScanNet's colour size after its export), resized as detectron2
does (shortest edge 800). PointRend's cost grows with the detections it refines, so each score
threshold is its own row: 0.05 is detectron2's (usl-segment's default, usually 100 detections per
frame), 0.5 is usl-convert-scannet's --min-score (the segmenter refines only those). Without
--weights, seeded random weights in detectron2's layout stand in (tests/model/detectron2_fixtures.py);
their detection counts are printed with the rates. Rates: wall-clock frames/s, and process CPU
seconds per frame (on CUDA: wall seconds, synchronised).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))

from tests.model.detectron2_fixtures import POINTREND, synthetic_picture, write_random_checkpoint  # noqa: E402
from usl.model.segmenter import InstanceSegmenter, SegmenterConfig  # noqa: E402


def measure(segmenter: InstanceSegmenter, frames: list[np.ndarray], batch_size: int) -> tuple[float, float, float]:
    """(frames/s wall, CPU or device seconds per frame, detections per frame) after one warm-up batch."""
    segmenter(frames[:batch_size])
    cuda = segmenter.device.type == "cuda"
    if cuda:
        torch.cuda.synchronize()
    wall, cpu = time.perf_counter(), time.process_time()
    found = 0
    for start in range(0, len(frames), batch_size):
        found += sum(len(r) for r in segmenter(frames[start : start + batch_size]))
    if cuda:
        torch.cuda.synchronize()
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    return len(frames) / wall, (wall if cuda else cpu) / len(frames), found / len(frames)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--weights", type=Path, help="detectron2 / torchvision weights (default: random PointRend)")
    p.add_argument("--frames", type=int, default=4, help="timed frames per row")
    p.add_argument("--size", type=int, nargs=2, default=(640, 480), metavar=("W", "H"), help="frame size")
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", default=f"1,{os.cpu_count()}", help="comma-separated torch thread counts")
    p.add_argument("--score-thresholds", type=float, nargs="+", default=(0.05, 0.5))
    p.add_argument("--batch-size", type=int, default=1)
    args = p.parse_args()

    frames = [synthetic_picture(seed, *args.size) for seed in range(args.frames)]
    with tempfile.TemporaryDirectory() as tmp:
        weights = args.weights
        if weights is None:
            weights = Path(tmp) / "pointrend.pkl"
            write_random_checkpoint(weights, POINTREND, seed=0)
        print(f"segmenter on {args.frames} frames of {args.size[0]}x{args.size[1]}, {args.device}, weights {weights}")
        print(f"{'threads':>7} {'score>':>6} {'dets/frame':>10} {'frames/s':>9} {'s/frame':>8}")
        for threads in [int(t) for t in args.threads.split(",")]:
            torch.set_num_threads(threads)
            for threshold in args.score_thresholds:
                segmenter = InstanceSegmenter.from_weights(
                    weights, SegmenterConfig(score_threshold=threshold), args.device
                )
                rate, seconds, found = measure(segmenter, frames, args.batch_size)
                print(f"{threads:>7} {threshold:>6.2f} {found:>10.1f} {rate:>9.3f} {seconds:>8.2f}", flush=True)


if __name__ == "__main__":
    main()
