"""Training-step benchmark: seconds per iteration, images/s and peak memory of ``usl-train``'s step.

    python scripts/bench/train.py --config tiny --device cpu                 # CPU, tiny recipe
    python scripts/bench/train.py --config hypersim --device cuda            # paper size: 768x1024,
                                                                             # 2 images x 5 views per GPU
    python scripts/bench/train.py --config tiny --data /data/scene_shapes_small   # real records

Without ``--data`` the batches are synthetic but shaped like the dataset of the recipe: images
of ``--size``, ``--objects`` objects per input view with elliptic masks, and ``num_views`` views
per sample whose masks sit at other places (the cost of a step does not depend on the masks
being consistent). The step is the trainer's own ``TrainStep`` (autocast, clipping, NaN guard,
optimizer); data loading is not timed, and on CUDA the batches are page-locked as the loader's are.
"""

from __future__ import annotations

import argparse
import resource
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the checkout: its tests' synthetic samples

from tests.data.synthetic_samples import synthetic_config, synthetic_sample  # noqa: E402
from usl.config import load_config  # noqa: E402
from usl.data import CategoryIndex, MultiViewDataset, SampleKey  # noqa: E402
from usl.engine.distributed import DistInfo  # noqa: E402
from usl.engine.train import fill_dataset_fields, seed_everything  # noqa: E402
from usl.engine.train_step import TrainStep  # noqa: E402
from usl.records import RecordsDataset  # noqa: E402

DEFAULT_SIZE = {
    "tiny": (128, 128),
    "scene_shapes": (512, 512),
    "scene_shapes_fpn": (512, 512),
    "hypersim": (768, 1024),
    "scannet": (968, 1296),
}
DEFAULT_OBJECTS = {"tiny": 2, "scene_shapes": 2, "scene_shapes_fpn": 2, "hypersim": 20, "scannet": 8}


def bench_step(
    args: argparse.Namespace,
    device: torch.device,
    num_batches: int,
    sizes: dict[str, tuple[int, int]],
    objects: dict[str, int],
    default_size: tuple[int, int],
) -> tuple[TrainStep, list[list]]:
    """The trainer's ``TrainStep`` for ``--config`` and ``num_batches`` batches: read from the ``--data``
    records, else synthetic ones of ``--size`` (default ``sizes[config]``) with ``--objects`` objects.
    Also what ``count_ops.py`` counts."""
    overrides = [f"train.batch_size={args.batch_size}"] if args.batch_size else []
    overrides += [*args.overrides, *([f"data.num_views={args.views}"] if args.views else [])]
    if args.data:
        cfg = load_config(args.config, overrides)
        records = RecordsDataset(args.data, cfg.data.train_split)
        fill_dataset_fields(cfg, records)
    else:
        cfg, records = synthetic_config(args.config, overrides), None
    seed_everything(cfg.train.seed, 0)
    step = TrainStep(cfg, DistInfo(0, 1, 0, device))
    size = cfg.train.batch_size
    if records is not None:
        dataset = MultiViewDataset(records, cfg.data, CategoryIndex(records.categories), cfg.train.seed)
        pool = [dataset[SampleKey(i % len(dataset), i // len(dataset))] for i in range(num_batches * size)]
    else:
        height, width = args.size or sizes.get(args.config, default_size)
        count = args.objects or objects.get(args.config, 10)
        classes = len(cfg.model.categories)
        pool = [
            synthetic_sample(i, height, width, count, cfg.data.num_views, classes) for i in range(num_batches * size)
        ]
    if device.type == "cuda":  # page-locked, as the trainer's loader hands them over
        pool = [sample.pin_memory() for sample in pool]
    return step, [pool[k * size : (k + 1) * size] for k in range(num_batches)]


def gpu_busy_fraction(train_step: TrainStep, batches: list[list], device: torch.device) -> float:
    """Fraction of the wall time of ``batches`` steps during which at least one kernel ran on the GPU:
    the union of the profiler's device-kernel intervals over the span of the steps. Far below 1, the
    GPU waits on the host (Python, launches, syncs), which no faster kernel can fix."""
    from torch.profiler import ProfilerActivity, profile

    torch.cuda.synchronize(device)
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        start = time.perf_counter()
        for batch in batches:
            train_step(batch)
        torch.cuda.synchronize(device)
        wall_us = (time.perf_counter() - start) * 1e6
    kernels = sorted(
        (e.time_range.start, e.time_range.end)
        for e in prof.events()
        if e.device_type == torch.autograd.DeviceType.CUDA and e.time_range.end > e.time_range.start
    )
    busy, reach = 0.0, float("-inf")
    for begin, end in kernels:  # union of intervals
        if end > reach:
            busy += end - max(begin, reach)
            reach = end
    return min(busy / wall_us, 1.0) if wall_us > 0 else 0.0


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--config", default="tiny")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    p.add_argument("--data", help="real records folder (default: synthetic batches)")
    p.add_argument("--iters", type=int, default=10, help="timed iterations")
    p.add_argument("--warmup", type=int, default=3)
    p.add_argument("--batch-size", type=int, default=0, help="default: the recipe's train.batch_size")
    p.add_argument("--size", type=int, nargs=2, metavar=("H", "W"), help="synthetic image size")
    p.add_argument("--objects", type=int, help="synthetic objects per input view")
    p.add_argument("--views", type=int, help="views per sample (default: the recipe's data.num_views)")
    p.add_argument("--threads", type=int, default=0, help="CPU intra-op threads (0: torch default)")
    p.add_argument("--busy-steps", type=int, default=3, help="CUDA: steps profiled for the GPU-busy fraction (0: skip)")
    p.add_argument("overrides", nargs="*", help="config overrides key=value")
    args = p.parse_args()
    device = torch.device(args.device)
    if args.threads:
        torch.set_num_threads(args.threads)
    train_step, batches = bench_step(args, device, 4, DEFAULT_SIZE, DEFAULT_OBJECTS, (768, 1024))
    cfg, batch_size = train_step.cfg, train_step.cfg.train.batch_size
    times, cpu_times = [], []  # wall clock; CPU time of this process (all its threads)
    for iteration in range(args.warmup + args.iters):
        batch = batches[iteration % len(batches)]
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        start, cpu_start = time.perf_counter(), time.process_time()
        values = train_step(batch)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        if iteration >= args.warmup:
            times.append(time.perf_counter() - start)
            cpu_times.append(time.process_time() - cpu_start)
    per_iter = statistics.median(times)
    images = batch_size
    print(
        f"config={args.config} device={device} batch={images} views={cfg.data.num_views} "
        f"stages={cfg.model.shape.num_stages} ico={cfg.model.shape.ico_level} render={cfg.loss.render.resolution} "
        f"amp={cfg.train.amp if device.type == 'cuda' else 'off'} data={'records' if args.data else 'synthetic'}"
    )
    print(f"  seconds/iteration (median of {len(times)}): {per_iter:.3f}   min {min(times):.3f}  max {max(times):.3f}")
    print(
        f"  CPU seconds/iteration (median, all threads; steady on a shared machine): {statistics.median(cpu_times):.3f}"
    )
    print(f"  images/s: {images / per_iter:.2f}   last loss {values['loss']:.4f}")
    if device.type == "cuda":
        print(f"  peak GPU memory: {torch.cuda.max_memory_allocated(device) / 2**30:.2f} GiB")
        if args.busy_steps:
            busy = gpu_busy_fraction(train_step, [batches[i % len(batches)] for i in range(args.busy_steps)], device)
            print(f"  GPU busy: {100 * busy:.0f}% of wall time ({args.busy_steps} steps, torch.profiler)")
    print(f"  peak process RSS: {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB")


if __name__ == "__main__":
    main()
