"""usl's NMS (the compiled CPU loop and the pure-torch graph method) against torchvision.ops,
side by side in one run (process CPU time, 1 thread).

    python scripts/bench/nms.py                              # in an env where torchvision imports
    python scripts/bench/nms.py --device cuda --sizes 1000 20000

Boxes look like detector output: clusters of jittered boxes around object-like boxes (what
proposals and per-class detections are) plus scattered background boxes; ``batched`` puts them
in 5 groups (FPN levels or classes). Prints per case the median process-CPU time (wall on CUDA)
of usl's ``nms``/``batched_nms`` (what the detector calls: the compiled loop on CPU), of the
pure-torch path (what runs on CUDA without torchvision), of torchvision's, the ratio torchvision /
usl, and whether the kept indices agree. Without torchvision its columns stay empty.
"""

from __future__ import annotations

import argparse
import statistics
import time
from functools import partial

import torch

from usl.model.ops import batched_nms, nms  # no compiled torch extension: imports beside any torchvision
from usl.model.ops.nms import _TORCHVISION, _pure_torch_batched_nms, _pure_torch_nms


def detector_like_boxes(count: int, generator: torch.Generator, size: float = 1024.0):
    objects = max(count // 40, 1)
    centre = torch.rand(objects, 2, generator=generator) * size
    extent = torch.rand(objects, 2, generator=generator) * 200 + 20
    owner = torch.randint(0, objects, (count,), generator=generator)
    jitter = torch.randn(count, 4, generator=generator) * 0.15
    c = centre[owner] + jitter[:, :2] * extent[owner]
    wh = extent[owner] * torch.exp(jitter[:, 2:])
    background = torch.rand(count, generator=generator) < 0.3  # scattered boxes of any size
    c = torch.where(background[:, None], torch.rand(count, 2, generator=generator) * size, c)
    wh = torch.where(background[:, None], torch.rand(count, 2, generator=generator) * 300 + 4, wh)
    boxes = torch.cat([c - wh / 2, c + wh / 2], dim=1)
    scores = torch.rand(count, generator=generator)
    groups = torch.randint(0, 5, (count,), generator=generator)
    return boxes, scores, groups


def timed(fn, device: torch.device, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        clock = time.perf_counter if device.type == "cuda" else time.process_time
        start = clock()
        fn()
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        times.append(clock() - start)
    return statistics.median(times)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", type=int, nargs="+", default=[1000, 5000, 20000])
    p.add_argument("--thresholds", type=float, nargs="+", default=[0.5, 0.7])
    p.add_argument("--device", default="cpu")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--pure-up-to", type=int, default=5000, help="time the pure-torch path up to this many boxes")
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    tv = _TORCHVISION  # torchvision.ops if it imports and its kernels run beside this torch
    print(
        f"torch {torch.__version__}, torchvision {'ops loaded' if tv else 'not available'}, device {device}, "
        f"{args.threads} thread(s); {'wall' if device.type == 'cuda' else 'process CPU'} ms, median of {args.repeats}"
    )
    print(f"{'case':>26} {'usl nms':>10} {'pure torch':>11} {'torchvision':>12} {'tv / usl':>9} {'same':>5}")
    for count in args.sizes:
        boxes, scores, groups = (t.to(device) for t in detector_like_boxes(count, torch.Generator().manual_seed(count)))
        for threshold in args.thresholds:
            for batched in (False, True):
                if batched:
                    ours = partial(batched_nms, boxes, scores, groups, threshold)
                    pure = partial(_pure_torch_batched_nms, boxes, scores, groups, threshold)
                    # torchvision's own batched_nms orders equal scores arbitrarily: compare the kept sets
                    theirs = tv and partial(tv.batched_nms, boxes, scores, groups, threshold)
                else:
                    ours = partial(nms, boxes, scores, threshold)
                    pure = partial(_pure_torch_nms, boxes, scores, threshold)
                    theirs = tv and partial(tv.nms, boxes, scores, threshold)
                case = f"{'batched' if batched else 'nms'} n={count} t={threshold}"
                t_ours = timed(ours, device, args.repeats)
                line = f"{case:>26} {t_ours * 1e3:8.2f}ms"
                if count <= args.pure_up_to:
                    assert torch.equal(ours(), pure()), f"{case}: usl's two paths disagree"
                    line += f" {timed(pure, device, args.repeats) * 1e3:9.2f}ms"
                else:
                    line += f" {'-':>11}"
                if theirs:
                    t_tv = timed(theirs, device, args.repeats)
                    kept, tv_kept = ours().cpu(), theirs().cpu()
                    same = torch.equal(kept, tv_kept) if not batched else set(kept.tolist()) == set(tv_kept.tolist())
                    line += f" {t_tv * 1e3:10.2f}ms {t_tv / t_ours:8.2f}x {str(same):>5}"
                print(line, flush=True)


if __name__ == "__main__":
    main()
