"""Ops and host syncs of one ``usl-train`` step: what grows with objects and views, and where.

    python scripts/bench/count_ops.py --config tiny --batch-size 4          # 4 images x 2 objects x 3 views, 128² (the budget's shape)
    python scripts/bench/count_ops.py --config hypersim --size 192 256 --objects 20   # 2 images x 20 x 5
    python scripts/bench/count_ops.py --config tiny --data /data/scene_shapes_small  # real records
    python scripts/bench/count_ops.py --config tiny --cpu-steps 20         # and CPU seconds per step
    python scripts/bench/count_ops.py --config tiny --predict detections   # usl-predict's model call
    python scripts/bench/count_ops.py --config tiny --compiled             # the CPU's compiled loops too

One step of the trainer's own ``TrainStep`` (forward, backward, clipping, guard, optimizer) after
``--warmup`` steps, counted with ``usl.utils.op_count``: ATen ops dispatched, host syncs by kind (the
points where a CUDA run waits for the device, copies to it from pageable host memory included; a
CPU run counts its copies as a CUDA run makes them), and the source lines causing most of each.
Counts are deterministic, so two commits compare exactly; ``--cpu-steps`` adds the median process
CPU time of that many uncounted steps (compare commits in one run, alternating, with OMP_NUM_THREADS=1).
``--predict MODE`` counts one ``USLModel.predict`` call on the batch's input views instead (what
usl-predict and usl-eval run per batch), with the trained-from-scratch weights of the step.

By default the step runs the torch paths a CUDA step runs, also on a CPU: on CPU tensors the soft
rasterizer, mask resampling, silhouette Chamfer and NMS are compiled loops (``usl.utils.compiled``)
that read their inputs on the host, which only the CPU pays; NMS counts its pure-torch path (CUDA
runs torchvision's kernel instead where torchvision is installed). ``--compiled`` counts the CPU's
own step (no device, so no uploads).
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import time

import torch
from train import bench_step  # scripts/bench/train.py: the same step and batches it times

from usl.utils.compiled import torch_paths_only
from usl.utils.op_count import count_ops, format_report

SIZE = {"tiny": (128, 128), "tiny_long": (128, 128), "hypersim": (192, 256), "scannet": (242, 324)}
OBJECTS = {"tiny": 2, "tiny_long": 2, "hypersim": 20, "scannet": 8}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--config", default="tiny")
    p.add_argument("--device", default="cpu")
    p.add_argument("--data", help="real records folder (default: synthetic batches)")
    p.add_argument("--batch-size", type=int, default=0, help="default: the recipe's train.batch_size")
    p.add_argument("--size", type=int, nargs=2, metavar=("H", "W"), help="synthetic image size")
    p.add_argument("--objects", type=int, help="synthetic objects per input view")
    p.add_argument("--views", type=int, help="views per sample (default: the recipe's data.num_views)")
    p.add_argument("--warmup", type=int, default=2)
    p.add_argument("--top", type=int, default=15, help="source lines listed")
    p.add_argument("--cpu-steps", type=int, default=0, help="also time this many uncounted steps")
    p.add_argument("--predict", choices=("gt_boxes", "detections"), help="count inference instead of a step")
    p.add_argument(
        "--compiled",
        action="store_true",
        help="CPU: count with the compiled loops (default: the torch paths CUDA runs)",
    )
    p.add_argument("overrides", nargs="*", help="config overrides key=value")
    args = p.parse_args()
    torch.set_num_threads(1)
    step, batches = bench_step(args, torch.device(args.device), 2, SIZE, OBJECTS, (192, 256))
    for iteration in range(args.warmup):
        step(batches[iteration % 2])
    frames = [sample.frame for sample in batches[args.warmup % 2]]
    paths = contextlib.nullcontext() if args.compiled else torch_paths_only()
    with paths, count_ops(as_on_accelerator=not args.compiled) as count:
        if args.predict:
            with torch.no_grad():
                step.model.predict(frames, args.predict)
        else:
            step(batches[args.warmup % 2])
    cfg = step.cfg
    objects = "data" if args.data else args.objects or OBJECTS.get(args.config, 10)
    print(
        f"config={args.config} images={cfg.train.batch_size} objects={objects} "
        f"views={cfg.data.num_views} data={'records' if args.data else 'synthetic'} "
        f"counted={'predict ' + args.predict if args.predict else 'training step'} "
        f"paths={'compiled CPU loops' if args.compiled else 'torch (as on CUDA)'}"
    )
    print(format_report(count, args.top))
    if args.cpu_steps:
        cpu = []
        for iteration in range(args.cpu_steps):
            start = time.process_time()
            step(batches[iteration % 2])
            cpu.append(time.process_time() - start)
        print(f"CPU seconds/step (median of {len(cpu)}, 1 thread): {statistics.median(cpu):.3f}")


if __name__ == "__main__":
    main()
