"""``usl-convert-scannet``: ScanNet scans + 2D instance masks, tracked into objects (paper Sec. 4.3).

Scans are read from ``--scans-root/<scan>/`` as ``<scan>.sens`` or as exported frame folders; the
scan lists come from the official ``scannetv2_<split>.txt`` files in ``--splits-dir``. Masks come
from a detections file (COCO results, e.g. PointRend run with detectron2) or from ScanNet's own
instance-filt/label-filt images. See pipelines/scannet/README.md for the file formats.

    usl-convert-scannet --out data/scannet --scans-root /data/scannet/scans --splits-dir /data/scannet/splits \\
        --masks model --weights model_final_edd263.pkl --workers 8
    usl-convert-scannet --out data/scannet --scans-root ... --splits-dir ... \\
        --detections pointrend_results.json --detection-images images.json --workers 8
    usl-convert-scannet --out data/scannet_gt --scans-root ... --splits-dir ... --masks scannet-labels \\
        --label-map scannetv2-labels.combined.tsv --tracker source-ids --resolution 320x240
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING

from data_specs import load_dataset_spec
from pipelines.common import (
    ShardPlan,
    add_build_arguments,
    build_common_options,
    build_options_from_args,
    creator_from_args,
    fingerprint_from_args,
    run_build,
    scratch_dir,
)
from usl.cli.common import DEVICE_CHOICES, make_parser, resolution
from usl.errors import UslError
from usl.records.names import check_name

if TYPE_CHECKING:  # the converter loads torch: imported where used, after parsing (fast --help)
    from .convert import ConvertOptions
    from .masks import MaskSource
    from .tracker import TrackerConfig

COMMAND = "usl-convert-scannet"
SPLITS = ("train", "val", "test")


def parse_size(text: str) -> tuple[int, int] | None:
    """``--resolution``: the shared ``WxH``-or-one-int syntax, or ``native``."""
    return None if text == "native" else resolution(text)


def add_segmenter_arguments(group: argparse._ArgumentGroup) -> None:
    """``--masks model``'s options (``--weights``, ``--device``, ``--segment-*``), read by ``model_source``."""
    group.add_argument(
        "--weights",
        type=Path,
        help="--masks model: detectron2 PointRend / Mask R-CNN .pkl or torchvision Mask R-CNN .pth (COCO)",
    )
    group.add_argument(
        "--device", choices=DEVICE_CHOICES, default="auto", help="--masks model: where the segmenter runs"
    )
    group.add_argument("--segment-batch-size", type=int, default=1, help="--masks model: frames per forward pass")
    group.add_argument(
        "--segment-size",
        type=int,
        nargs=2,
        default=(800, 1333),
        metavar=("MIN", "MAX"),
        help="--masks model: frames are resized to this shortest edge, longest at most MAX (detectron2's test size)",
    )


def add_detection_arguments(group: argparse._ArgumentGroup) -> None:
    """How a COCO results file names categories, and the score below which detections are ignored."""
    group.add_argument(
        "--category-ids",
        choices=("coco", "contiguous"),
        default="coco",
        help="coco: category_id is a COCO id (1..90); contiguous: detectron2's 0-based class index",
    )
    group.add_argument("--min-score", type=float, default=0.5, help="ignore detections less confident than this")


def add_encoding_arguments(group: argparse._ArgumentGroup) -> None:
    """What the records store of a frame besides its masks: JPEG quality of re-encoded images, depth."""
    group.add_argument(
        "--jpeg-quality", type=int, default=95, metavar="Q", help="for re-encoded (resized) images (1..100)"
    )
    group.add_argument("--no-depth", action="store_true", help="do not store depth images in the records")


def add_tracking_arguments(group: argparse._ArgumentGroup, spec: dict) -> None:
    """The IoU tracker's options (read by ``tracker_config``) and the depth warp's tolerance."""
    group.add_argument("--iou-threshold", type=float, default=0.5, help="mask IoU continuing a track")
    group.add_argument("--max-missed", type=int, default=3, help="processed frames a track may go unmatched")
    group.add_argument(
        "--min-track-frames",
        type=int,
        default=int(spec["tracking"]["min_track_frames"]),
        help="observations (processed frames) a track needs to become an object",
    )
    group.add_argument(
        "--match-across-categories",
        action="store_true",
        help="let a detection continue a track of another category (the track's category is then "
        "the score-weighted vote)",
    )
    group.add_argument("--depth-tolerance", type=float, default=0.2, help="metres, for the warp's visibility test")


def tracker_config(args: argparse.Namespace) -> TrackerConfig:
    """``add_tracking_arguments``' options as the tracker's config (ValueError if out of range)."""
    from .tracker import TrackerConfig

    return TrackerConfig(args.iou_threshold, args.max_missed, args.min_track_frames, args.match_across_categories)


def parser(spec: dict) -> argparse.ArgumentParser:
    p = make_parser(COMMAND, __doc__, parents=[build_common_options()])
    add_build_arguments(p, skip_bad_scenes=True)
    p.add_argument("--scans-root", type=Path, required=True, help="folder with one <scan id>/ folder per scan")
    p.add_argument("--splits-dir", type=Path, required=True, help="folder with scannetv2_{train,val,test}.txt")
    p.add_argument("--splits", nargs="+", choices=SPLITS, default=["train", "val"], help="official splits to convert")
    p.add_argument("--scenes", nargs="+", default=None, help="convert only these scans (must be in --splits)")
    p.add_argument("--scenes-per-shard", type=int, default=8, help="scans per output shard")
    masks = p.add_argument_group("mask source")
    masks.add_argument(
        "--masks",
        choices=("detections", "model", "scannet-labels"),
        default="detections",
        help="detections: a 2D segmenter's COCO results; model: run usl's segmenter on the frames (--weights); "
        "scannet-labels: ScanNet's own instance images",
    )
    add_segmenter_arguments(masks)
    masks.add_argument("--detections", nargs="+", help="COCO results JSON file(s) from the segmenter")
    masks.add_argument("--detection-images", type=Path, help="COCO images JSON mapping image_id to scan frames")
    add_detection_arguments(masks)
    masks.add_argument("--label-map", type=Path, help="scannetv2-labels.combined.tsv (for --masks scannet-labels)")
    frames = p.add_argument_group("frames")
    frames.add_argument("--stride", type=int, default=10, help="process every N-th frame of a scan")
    # dest "size" as before the rename, so build fingerprints (and resuming) are unchanged
    frames.add_argument(
        "--resolution",
        dest="size",
        type=parse_size,
        default=(640, 480),
        metavar="WxH",
        help="output resolution (one int: square), or 'native' to keep the colour frames (and their JPEG bytes)",
    )
    add_encoding_arguments(frames)
    track = p.add_argument_group("tracking")
    track.add_argument(
        "--tracker",
        choices=("iou", "source-ids"),
        default="iou",
        help="source-ids: use ScanNet's instance ids as tracks (only with --masks scannet-labels)",
    )
    add_tracking_arguments(track, spec)
    track.add_argument(
        "--warp",
        choices=("auto", "on", "off"),
        default="auto",
        help="warp the last mask of a track into the current frame with depth and pose (auto: when --stride > 1)",
    )
    return p


def read_split(splits_dir: Path, split: str) -> list[str]:
    path = splits_dir / f"scannetv2_{split}.txt"
    try:
        lines = path.read_text().splitlines()
    except OSError as exc:
        raise UslError(f"{path}: cannot read the official split file ({exc.strerror})") from None
    scenes = [check_name(line.strip(), "scan id", f"{path}:{n}") for n, line in enumerate(lines, 1) if line.strip()]
    if not scenes:
        raise UslError(f"{path}: lists no scans")
    return scenes


def scenes_by_split(args: argparse.Namespace) -> dict[str, list[str]]:
    chosen = {split: read_split(args.splits_dir, split) for split in args.splits}
    if args.scenes is not None:
        wanted = set(args.scenes)
        unknown = wanted - {s for scenes in chosen.values() for s in scenes}
        if unknown:
            raise UslError(f"--scenes {' '.join(sorted(unknown))} not in the {'/'.join(args.splits)} split files")
        chosen = {split: [s for s in scenes if s in wanted] for split, scenes in chosen.items()}
    missing = [s for scenes in chosen.values() for s in scenes if not (args.scans_root / s).is_dir()]
    if missing:
        raise UslError(
            f"{args.scans_root}: {len(missing)} scan folder(s) missing, e.g. {', '.join(missing[:5])}; "
            "restrict the build with --scenes or --splits"
        )
    return {split: scenes for split, scenes in chosen.items() if scenes}


def convert_options(args: argparse.Namespace) -> ConvertOptions:
    from .convert import ConvertOptions

    try:
        tracker = tracker_config(args)
        return ConvertOptions(
            args.stride,
            args.size,
            args.jpeg_quality,
            not args.no_depth,
            args.min_score,
            args.warp,
            args.depth_tolerance,
            tracker,
            args.tracker == "source-ids",
        )
    except ValueError as exc:
        raise UslError(f"bad option: {exc}") from None


def mask_source(
    args: argparse.Namespace, spec: dict, scenes: set[str], cache: Path
) -> tuple[MaskSource, dict, Callable[[], None] | None]:
    """The mask source, what of its inputs belongs in the build fingerprint, and what must run once
    the output folder is known to hold this build (splitting the detections into ``cache``)."""
    from .detections_file import DetectionsFileSource, split_detections
    from .scannet_labels import ScanNetLabelsSource

    categories = spec["categories"]
    coco_to_category = tuple((int(c["coco_id"]), int(c["id"])) for c in categories)
    if args.masks == "scannet-labels":
        if args.label_map is None:
            raise UslError("--masks scannet-labels needs --label-map scannetv2-labels.combined.tsv")
        return ScanNetLabelsSource(str(args.label_map), tuple((int(c["id"]), c["name"]) for c in categories)), {}, None
    if args.tracker == "source-ids":
        raise UslError("--tracker source-ids needs --masks scannet-labels (detectors give no identities)")
    if args.masks == "model":
        return model_source(args, coco_to_category), model_fingerprint(args), None
    if not args.detections or args.detection_images is None:
        raise UslError("--masks detections needs --detections RESULTS.json and --detection-images IMAGES.json")
    results = [Path(p) for p in args.detections]
    files = [*results, args.detection_images]
    for path in files:
        if not path.is_file():
            raise UslError(f"{path}: no such file")
    source = DetectionsFileSource(str(cache), coco_to_category, args.category_ids == "contiguous")
    stamps = [[str(p), p.stat().st_size, p.stat().st_mtime_ns] for p in files]
    return source, {"detection_files": stamps}, partial(split_detections, results, args.detection_images, scenes, cache)


def model_source(args: argparse.Namespace, coco_to_category: tuple[tuple[int, int], ...]) -> MaskSource:
    """``--masks model``: the segmenter's description; each build worker loads it when a scan needs it.

    Reads ``add_segmenter_arguments``' options and ``--out``, ``--stride``, ``--min-score``."""
    from usl.cli.common import resolve_device
    from usl.model.segmenter import SegmenterConfig

    from .model_masks import SegmenterSource, segments_dir

    if args.weights is None:
        raise UslError("--masks model needs --weights FILE (detectron2 PointRend .pkl, e.g. model_final_edd263.pkl)")
    if not args.weights.is_file():
        raise UslError(f"{args.weights}: no such file")
    min_size, max_size = args.segment_size
    if min(min_size, max_size, args.segment_batch_size) < 1:
        raise UslError("--segment-size and --segment-batch-size must be >= 1")
    return SegmenterSource(
        str(args.weights.resolve()),
        str(segments_dir(args.out)),
        coco_to_category,
        args.stride,
        args.min_score,
        # detections below --min-score are dropped anyway: the box head drops them before NMS (which
        # keeps the same better ones) and the mask head never refines them
        SegmenterConfig(min_size=min_size, max_size=max_size, score_threshold=max(args.min_score, 0.05)),
        resolve_device(args.device),
        args.segment_batch_size,
    )


def model_fingerprint(args: argparse.Namespace) -> dict:
    """The weights file (path, size, modification time) and the segmenter's resize: cached detections
    belong to the build that made them. Device and batch size change no result."""
    stat = args.weights.stat()
    return {"segmenter": {"weights": [str(args.weights.resolve()), stat.st_size, stat.st_mtime_ns]}}


def plan_shards(
    chosen: dict[str, list[str]], scans_root: Path, per_shard: int, masks: MaskSource, options: ConvertOptions
) -> list[ShardPlan]:
    from .convert import ScanUnit

    plans = []
    for split, scenes in chosen.items():
        for index, start in enumerate(range(0, len(scenes), per_shard)):
            units = [ScanUnit(s, str(scans_root / s), masks, options) for s in scenes[start : start + per_shard]]
            plans.append(ShardPlan(split, index, units))
    return plans


def single_threaded_worker() -> None:
    """Workers parallelise over scans; threads inside one only contend (torch/OpenCV on small arrays)."""
    import cv2
    import torch

    torch.set_num_threads(1)
    cv2.setNumThreads(1)


def main(argv: list[str] | None = None) -> int:
    spec = load_dataset_spec("scannet")
    args = parser(spec).parse_args(argv)
    try:
        build = build_options_from_args(args)
        if args.scenes_per_shard < 1:
            raise UslError("--scenes-per-shard must be >= 1")
        options = convert_options(args)
        chosen = scenes_by_split(args)
        # The per-scan detections live in this run's scratch folder inside --out: removed when the run
        # ends, and reaped by the next run on this --out if this one is killed.
        cache = scratch_dir(args.out) / "detections"
        masks, inputs, prepare = mask_source(args, spec, {s for scenes in chosen.values() for s in scenes}, cache)
        plans = plan_shards(chosen, args.scans_root, args.scenes_per_shard, masks, options)
        fingerprint = {**fingerprint_from_args(args), **inputs}
        from .convert import build_scene

        summary = run_build(
            build,
            spec,
            fingerprint,
            plans,
            build_scene,
            creator_from_args(COMMAND, args),
            worker_initializer=single_threaded_worker,
            prepare=prepare,
        )
    except UslError as exc:
        print(f"{COMMAND}: error: {exc}", file=sys.stderr)
        return 2
    print(f"{COMMAND}: {summary.describe()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
