"""Benchmark of usl-convert-scannet: .sens decoding + tracking speed per core, and memory vs scan length.

Synthetic ScanNet-like scans (``tests.pipelines.scannet.synthetic_scan``; ten boxes, noisy depth so zlib
payloads are realistic) are written as .sens files with detectron2-style detections files, then:

* pass 1 (decode pose/depth + read detections + track) in frames per CPU-second (one thread), at stride 1, and
  at stride 10 with depth+pose warping (per processed frame);
* the whole scene conversion (pass 1 + pass 2: encode image, depth, masks) in frames/s;
* peak RSS of pass 1 and of a whole conversion for 200 vs 800 frames (separate processes).

Target: >= 30 frames/s/core for decoding + tracking at 640x480.
With ``--quality SCAN_DIR --label-map TSV`` it instead measures the IoU tracker against ScanNet's own
instance ids on a real scan (purity, id switches) at the given ``--stride``.

    python scripts/bench/scannet.py [--frames 400] [--work /tmp/bench_scannet]
"""

from __future__ import annotations

import argparse
import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # per-core numbers: one thread everywhere

import json  # noqa: E402
import shutil  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the checkout: its tests' synthetic scans

from data_specs import load_dataset_spec  # noqa: E402
from pipelines.common import BuildOptions, ShardPlan, run_build  # noqa: E402
from pipelines.scannet.convert import (  # noqa: E402
    ConvertOptions,
    ScanUnit,
    build_scene,
    open_scan,  # noqa: E402
    scene_frames,
    track_scan,
)
from pipelines.scannet.detections_file import DetectionsFileSource, split_detections  # noqa: E402
from pipelines.scannet.grid import OutputGrid  # noqa: E402
from pipelines.scannet.quality import tracking_quality  # noqa: E402
from pipelines.scannet.scannet_labels import ScanNetLabelsSource  # noqa: E402
from pipelines.scannet.tracker import TrackerConfig  # noqa: E402
from tests.pipelines.scannet.synthetic_scan import (  # noqa: E402
    Box,
    SyntheticFrame,
    SyntheticScan,
    detections_from_instances,
    write_sens,
)

SPEC = load_dataset_spec("scannet")
MAPPING = tuple((int(c["coco_id"]), int(c["id"])) for c in SPEC["categories"])
CATEGORIES = tuple((int(c["id"]), c["name"]) for c in SPEC["categories"])
PERIOD = 200  # the camera goes back and forth: frame i looks like frame PERIOD - i, so few renders serve many frames
COCO = (62, 63, 72, 67, 44, 64, 84, 62, 73, 65)
BOXES = tuple(
    Box(
        k + 1,
        COCO[k],
        2,
        (-1.6 + 0.36 * k, 0.3 + 0.5 * (k % 3), 0.3 + 0.1 * (k % 4)),
        (0.16, 0.2, 0.3),
        (40 + 20 * k, 200 - 15 * k, 90 + 10 * (k % 5)),
    )
    for k in range(10)
)


@dataclass(frozen=True)
class Config:
    name: str
    color: tuple[int, int]
    depth: tuple[int, int]
    out: tuple[int, int] | None  # output size; None = native colour


CONFIGS = (
    Config("640x480", (640, 480), (640, 480), (640, 480)),
    Config("1296x968 -> 640x480", (1296, 968), (640, 480), (640, 480)),
    Config("1296x968 native", (1296, 968), (640, 480), None),
)


def one_thread() -> None:
    torch.set_num_threads(1)
    cv2.setNumThreads(1)


def make_scan(work: Path, config: Config, num_frames: int) -> tuple[Path, DetectionsFileSource]:
    """A .sens scan of num_frames frames plus its split detections; cached on disk by name."""
    tag = f"{config.color[0]}x{config.color[1]}-{num_frames}"
    scene = "scene0100_00"
    scan_dir = work / tag / scene
    cache = work / tag / "cache"
    if (cache / f"{scene}.jsonl").exists():
        return scan_dir, DetectionsFileSource(str(cache), MAPPING)
    scan_dir.mkdir(parents=True, exist_ok=True)
    synthetic = SyntheticScan(
        num_frames=num_frames,
        color_size=config.color,
        depth_size=config.depth,
        boxes=BOXES,
        period=PERIOD,
        render_scale=4,
        depth_noise_mm=2.0,
        x_range=(-1.5, 1.5),
    )
    rendered: dict[int, tuple[SyntheticFrame, list[dict]]] = {}
    rng = np.random.default_rng(0)

    def frame(i: int) -> tuple[SyntheticFrame, list[dict]]:
        phase = i % PERIOD
        key = min(phase, PERIOD - phase)
        if key not in rendered:
            f = synthetic.render(key)
            rendered[key] = (f, detections_from_instances(f, synthetic, rng))
        f, dets = rendered[key]
        return SyntheticFrame(i, f.pose, f.color, f.depth_mm, f.instances), dets

    write_sens(scan_dir / f"{scene}.sens", synthetic, (frame(i)[0] for i in range(num_frames)))
    width, height = config.color
    images = [
        {"id": i, "file_name": f"{scene}/color/{i}.jpg", "width": width, "height": height} for i in range(num_frames)
    ]
    results = [
        {"image_id": i, **{k: v for k, v in d.items() if k != "true_instance"}}
        for i in range(num_frames)
        for d in frame(i)[1]
    ]
    (work / tag / "images.json").write_text(json.dumps(images))
    (work / tag / "results.json").write_text(json.dumps(results))
    split_detections([work / tag / "results.json"], work / tag / "images.json", {scene}, cache)
    return scan_dir, DetectionsFileSource(str(cache), MAPPING)


def options(config: Config, stride: int) -> ConvertOptions:
    return ConvertOptions(stride=stride, size=config.out, tracker=TrackerConfig(min_track_frames=max(1, 50 // stride)))


def speed(work: Path, config: Config, num_frames: int) -> dict[str, float]:
    scan_dir, source = make_scan(work, config, num_frames)
    out: dict[str, float] = {}
    with open_scan(scan_dir, "scene0100_00") as scan:
        start = time.process_time()
        masks = source.open_scan(scan)
        out["load detections s"] = time.process_time() - start
        grid = OutputGrid.for_scan(scan.calibration, config.out)
        for stride in (1, 10):
            opts = options(config, stride)
            start = time.process_time()
            tracked = track_scan(scan, masks, grid, opts)
            seconds = time.process_time() - start
            label = "decode+track fps" + (" (stride 10, warp)" if stride > 1 else "")
            out[label] = len(tracked.poses) / seconds
            if stride == 1:
                out["detections/frame"] = tracked.num_detections / len(tracked.poses)
                start = time.process_time()
                rows = list(scene_frames(scan, tracked, grid, opts))
                out["encode fps (pass 2)"] = len(rows) / (time.process_time() - start)
                out["record MB/frame"] = (
                    sum(len(r["image"]["bytes"]) + len((r["depth"] or {"bytes": b""})["bytes"]) for r in rows)
                    / len(rows)
                    / 2**20
                )
    start = time.process_time()
    record = build_scene(ScanUnit("scene0100_00", str(scan_dir), source, options(config, 1)))
    out["whole scene fps"] = len(record.frames) / (time.process_time() - start)
    return out


def peak_rss(work: Path, config: Config, num_frames: int, mode: str) -> float:
    """Peak RSS (MiB) of a fresh process running pass 1 ('track') or the whole conversion ('build')."""
    make_scan(work, config, num_frames)
    cmd = [sys.executable, __file__, "--work", str(work), "--rss", mode, str(num_frames), config.name]
    return float(subprocess.run(cmd, check=True, capture_output=True, text=True).stdout.strip().splitlines()[-1])


def high_water_mib() -> float:
    """Peak resident memory of this process (VmHWM; unlike ru_maxrss it does not inherit the parent's)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("no VmHWM in /proc/self/status")


def rss_child(work: Path, mode: str, num_frames: int, name: str) -> None:
    config = next(c for c in CONFIGS if c.name == name)
    scan_dir, source = make_scan(work, config, num_frames)
    if mode == "track":
        with open_scan(scan_dir, "scene0100_00") as scan:
            grid = OutputGrid.for_scan(scan.calibration, config.out)
            track_scan(scan, source.open_scan(scan), grid, options(config, 1))
    else:  # the whole conversion as usl-convert-scannet runs it: worker and shard writer in this process
        out = work / f"records-{num_frames}"
        shutil.rmtree(out, ignore_errors=True)
        unit = ScanUnit("scene0100_00", str(scan_dir), source, options(config, 1))
        run_build(BuildOptions(out, progress=False), SPEC, {}, [ShardPlan("train", 0, [unit])], build_scene, {})
        shutil.rmtree(out)
    print(f"{high_water_mib():.1f}")


def quality(scan_dir: Path, label_map: Path, stride: int) -> None:
    """The IoU tracker against ScanNet's consistent instance ids on a real scan."""
    scene_id = scan_dir.name
    with open_scan(scan_dir, scene_id) as scan:
        grid = OutputGrid.for_scan(scan.calibration, (640, 480))
        masks = ScanNetLabelsSource(str(label_map), CATEGORIES).open_scan(scan)
        start = time.process_time()
        opts = ConvertOptions(stride=stride)
        tracked = track_scan(scan, masks, grid, opts)
        seconds = time.process_time() - start
    observations = [
        (f, t.track_id, d.source_id) for t in tracked.tracks for f, d in zip(t.frames, t.detections, strict=True)
    ]
    print(
        f"{scene_id} stride {stride}: {tracking_quality(observations).describe()}; {len(tracked.objects)} objects "
        f"of >= {opts.tracker.min_track_frames} frames; {len(tracked.poses)} frames in {seconds:.1f} s"
    )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--frames", type=int, default=400, help="frames per synthetic scan for the speed runs")
    p.add_argument("--work", type=Path, default=Path("/tmp/bench_scannet"))
    p.add_argument("--keep", action="store_true", help="keep the synthetic scans in --work")
    p.add_argument("--rss", nargs=3, metavar=("MODE", "FRAMES", "CONFIG"), help=argparse.SUPPRESS)
    p.add_argument("--quality", type=Path, metavar="SCAN_DIR", help="a real ScanNet scan folder with instance-filt")
    p.add_argument("--label-map", type=Path, help="scannetv2-labels.combined.tsv (with --quality)")
    p.add_argument("--stride", type=int, default=10, help="frame stride (with --quality)")
    args = p.parse_args()
    one_thread()
    if args.rss:
        rss_child(args.work, args.rss[0], int(args.rss[1]), args.rss[2])
        return
    if args.quality:
        quality(args.quality, args.label_map, args.stride)
        return
    args.work.mkdir(parents=True, exist_ok=True)
    try:
        print(f"one thread; {args.frames} frames per scan; {len(BOXES)} objects")
        results = {}
        for config in CONFIGS:
            results[config.name] = speed(args.work, config, args.frames)
            print(config.name + ": " + ", ".join(f"{k} {v:.2f}" for k, v in results[config.name].items()), flush=True)
        config = CONFIGS[1]
        for mode in ("track", "build"):
            rss = {n: peak_rss(args.work, config, n, mode) for n in (200, 800)}
            what = "pass 1 (decode+track)" if mode == "track" else "whole conversion (run_build, 1 worker)"
            print(
                f"peak RSS, {config.name}, {what}: 200 frames {rss[200]:.0f} MiB, 800 frames {rss[800]:.0f} MiB "
                f"(+{rss[800] - rss[200]:.0f} MiB for 4x the frames)",
                flush=True,
            )
            results[f"rss {mode}"] = rss
        target = results["640x480"]["decode+track fps"]
        verdict = "met" if target >= 30 else "MISSED"
        print(f"decode+track at 640x480: {target:.1f} frames/s/core (target >= 30: {verdict})")
        print(json.dumps(results))
    finally:
        if not args.keep:
            shutil.rmtree(args.work, ignore_errors=True)


if __name__ == "__main__":
    main()
