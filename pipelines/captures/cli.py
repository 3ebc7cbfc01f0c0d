"""``usl-convert-captures``: your own captures (a phone video, a capture app's export) -> records, objects tracked.

Each capture is a folder (ROOT itself, or each capture folder in ROOT) holding ``transforms.json``
(nerfstudio, instant-ngp, Polycam, Record3D), a COLMAP model (``sparse/0``, ``colmap/sparse/0``), or
only frames (``images/`` or a video file, with ``--poses sfm``). Masks come from each capture's
``detections.json`` (``usl-segment``'s output) or from usl's segmenter (``--masks model``). See
pipelines/captures/README.md and docs/captures.md.

    usl-convert-captures captures/ --out records/mine --workers 2
    usl-convert-captures kitchen/ --out records/kitchen --poses sfm --fps 3 --masks model --weights model_final_edd263.pkl
"""

from __future__ import annotations

import argparse
import sys
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
)
from pipelines.scannet.cli import (
    add_detection_arguments,
    add_encoding_arguments,
    add_segmenter_arguments,
    add_tracking_arguments,
    model_fingerprint,
    model_source,
    single_threaded_worker,
    tracker_config,
)
from usl.cli.common import make_parser, resolution
from usl.errors import UslError
from usl.records.names import check_name

if TYPE_CHECKING:  # the converter loads torch: imported where used, after parsing (fast --help)
    from pipelines.scannet.convert import ConvertOptions
    from pipelines.scannet.masks import MaskSource

    from .convert import PoseOptions
    from .layout import CaptureSource

COMMAND = "usl-convert-captures"


def output_resolution(text: str) -> tuple[int, int] | str:
    """``--resolution``: ``WxH`` (one int: square) or ``native``."""
    return text if text == "native" else resolution(text)


def output_size(args: argparse.Namespace) -> tuple[tuple[int, int] | None, int | None]:
    """(fixed output size or None for the capture's own, longest side to fit or None)."""
    if args.size is None:
        return None, args.max_side
    return (None if args.size == "native" else args.size), None


def parser(spec: dict) -> argparse.ArgumentParser:
    p = make_parser(COMMAND, __doc__, parents=[build_common_options()])
    add_build_arguments(p, skip_bad_scenes=False)
    p.add_argument("root", type=Path, help="a capture folder, or a folder of capture folders")
    p.add_argument("--split", default="train", help="the split the captures go to (but those of --val)")
    p.add_argument("--val", nargs="+", default=[], metavar="CAPTURE", help="captures (folder names) for split val")
    p.add_argument("--scenes-per-shard", type=int, default=8, help="captures per output shard")
    poses = p.add_argument_group("poses")
    poses.add_argument(
        "--poses",
        choices=("given", "sfm"),
        default="given",
        help="given: transforms.json, else a COLMAP model; sfm: solve them from images/ or the video with pycolmap",
    )
    poses.add_argument(
        "--scale",
        type=float,
        default=None,
        help="metres per unit of the poses (default: transforms.json is metric; COLMAP/SfM take it from depth "
        "maps, else assume the SfM points' median depth is 2 m)",
    )
    poses.add_argument("--fps", type=float, default=3.0, help="frames per second taken from a video")
    poses.add_argument(
        "--sfm-camera-model",
        choices=("SIMPLE_RADIAL", "OPENCV", "PINHOLE", "SIMPLE_PINHOLE", "RADIAL"),
        default="SIMPLE_RADIAL",
        help="--poses sfm: the one camera of a capture",
    )
    poses.add_argument("--sfm-max-features", type=int, default=4096, help="--poses sfm: SIFT features per image")
    poses.add_argument("--sfm-max-image-size", type=int, default=1600, help="--poses sfm: longest side SIFT sees")
    poses.add_argument("--sfm-overlap", type=int, default=10, help="--poses sfm: frames each frame is matched with")
    poses.add_argument("--sfm-threads", type=int, default=-1, help="--poses sfm: threads (-1: all cores)")
    masks = p.add_argument_group("mask source")
    masks.add_argument(
        "--masks",
        choices=("detections", "model"),
        default="detections",
        help="detections: each capture's detections.json (usl-segment's output); model: run usl's segmenter",
    )
    add_segmenter_arguments(masks)
    add_detection_arguments(masks)
    frames = p.add_argument_group("frames")
    frames.add_argument("--stride", type=int, default=1, help="process every N-th frame of a capture")
    frames.add_argument(
        "--resolution",
        dest="size",
        type=output_resolution,
        default=None,
        metavar="WxH",
        help="output resolution, or 'native'; default: the longest side fitted to --max-side",
    )
    frames.add_argument("--max-side", type=int, default=640, help="longest output side when --resolution is not given")
    add_encoding_arguments(frames)
    track = p.add_argument_group("tracking")
    add_tracking_arguments(track, spec)
    track.add_argument(
        "--no-warp",
        action="store_true",
        help="compare masks in place even when the capture has depth (default: warp a track's last mask "
        "into the current frame with depth and the relative pose)",
    )
    return p


def convert_options(args: argparse.Namespace) -> tuple[ConvertOptions, PoseOptions]:
    from pipelines.scannet.convert import ConvertOptions

    from .convert import PoseOptions
    from .sfm import SfmOptions

    try:
        if args.max_side < 1:
            raise ValueError(f"--max-side must be >= 1, got {args.max_side}")
        options = ConvertOptions(
            args.stride,
            output_size(args)[0],
            args.jpeg_quality,
            not args.no_depth,
            args.min_score,
            "off" if args.no_warp else "on",
            args.depth_tolerance,
            tracker_config(args),
        )
        sfm = SfmOptions(
            args.sfm_camera_model, args.sfm_max_features, args.sfm_max_image_size, args.sfm_overlap, args.sfm_threads
        )
        return options, PoseOptions(args.scale, args.fps, sfm)
    except ValueError as exc:
        raise UslError(f"bad option: {exc}") from None


def mask_source(
    args: argparse.Namespace, spec: dict, captures: list[tuple[str, Path, CaptureSource]]
) -> tuple[MaskSource, dict]:
    """The mask source and what of its inputs belongs in the build fingerprint."""
    from .detections import DETECTIONS, CaptureDetectionsSource

    coco_to_category = tuple((int(c["coco_id"]), int(c["id"])) for c in spec["categories"])
    if args.masks == "model":
        return model_source(args, coco_to_category), model_fingerprint(args)
    stamps = []
    for _, folder, _ in captures:
        path = folder / DETECTIONS
        if not path.is_file():
            raise UslError(f"{path}: no such file (run usl-segment on the capture's frames, or pass --masks model)")
        stamps.append([str(path), path.stat().st_size, path.stat().st_mtime_ns])
    return CaptureDetectionsSource(coco_to_category, args.category_ids == "contiguous"), {"detection_files": stamps}


def plan_shards(units: list, split: str, val: set[str], per_shard: int) -> list[ShardPlan]:
    """``--val`` captures to split val, the rest to ``split``, ``per_shard`` captures a shard."""
    unknown = val - {u.scene_id for u in units}
    if unknown:
        raise UslError(f"--val {' '.join(sorted(unknown))}: no such capture")
    if val and split == "val":
        raise UslError("--val needs --split other than val")
    groups = {split: [u for u in units if u.scene_id not in val], "val": [u for u in units if u.scene_id in val]}
    return [
        ShardPlan(name, k, chosen[start : start + per_shard])
        for name, chosen in groups.items()
        for k, start in enumerate(range(0, len(chosen), per_shard))
    ]


def main(argv: list[str] | None = None) -> int:
    spec = load_dataset_spec("captures")
    args = parser(spec).parse_args(argv)
    try:
        build = build_options_from_args(args)
        if args.scenes_per_shard < 1:
            raise UslError("--scenes-per-shard must be >= 1")
        split = check_name(args.split, "split", "--split")
        from .convert import CaptureUnit, build_scene, work_dir
        from .layout import find_captures

        options, poses = convert_options(args)
        captures = find_captures(args.root, args.poses == "sfm")
        masks, inputs = mask_source(args, spec, captures)
        max_side = output_size(args)[1]
        units = [
            CaptureUnit(scene, str(folder), source, masks, options, poses, str(work_dir(args.out, scene)), max_side)
            for scene, folder, source in captures
        ]
        plans = plan_shards(units, split, set(args.val), args.scenes_per_shard)
        summary = run_build(
            build,
            spec,
            {**fingerprint_from_args(args), **inputs},
            plans,
            build_scene,
            creator_from_args(COMMAND, args),
            worker_initializer=single_threaded_worker,
        )
    except UslError as exc:
        print(f"{COMMAND}: error: {exc}", file=sys.stderr)
        return 2
    print(f"{COMMAND}: {summary.describe()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
