"""``usl-convert-hypersim``: convert downloaded Hypersim scenes into multi-view records.

Examples::

    usl-convert-hypersim /data/hypersim --split-csv metadata_images_split_scene_v1.csv \\
        --camera-csv metadata_camera_parameters.csv --out /data/usl/hypersim --workers 8
    usl-convert-hypersim /data/hypersim/ai_001_001 --split-csv ... --camera-csv ... --out /tmp/hs \\
        --resolution 512x384 --stride 10 --exclude-categories stuff
"""

from __future__ import annotations

import argparse
import hashlib
import sys
from pathlib import Path

from data_specs import load_dataset_spec
from pipelines.common import (
    add_build_arguments,
    build_common_options,
    build_options_from_args,
    creator_from_args,
    fingerprint_from_args,
    run_build,
)
from usl.cli.common import make_parser
from usl.cli.common import resolution as parse_size
from usl.errors import UslError
from usl.records import load_manifest

from .metadata import read_camera_csv, read_split_csv
from .paths import INPUT_FORMATS
from .report import describe_dataset

COMMAND = "usl-convert-hypersim"
STUFF = ("wall", "floor", "ceiling")


def parser() -> argparse.ArgumentParser:
    p = make_parser(COMMAND, __doc__, parents=[build_common_options()])
    p.add_argument("scenes", nargs="+", help="scene folders (ai_VVV_NNN) or folders holding them")
    p.add_argument("--split-csv", type=Path, required=True, help="metadata_images_split_scene_v1.csv")
    p.add_argument("--camera-csv", type=Path, required=True, help="metadata_camera_parameters.csv")
    add_build_arguments(p, skip_bad_scenes=True)
    p.add_argument("--splits", nargs="+", default=[], help="splits to convert, e.g. train val; empty: all")
    p.add_argument("--cameras", nargs="+", default=[], help="camera trajectories to convert, e.g. cam_00; empty: all")
    # dest names stay as before the rename, so build fingerprints (and resuming) are unchanged
    p.add_argument(
        "--stride",
        dest="frame_stride",
        type=int,
        default=1,
        metavar="N",
        help="convert frames whose number is a multiple of this",
    )
    p.add_argument("--blacklist", nargs="+", default=[], help="scenes or scene/camera to leave out")
    p.add_argument("--blacklist-file", type=Path, default=None, help="more blacklist entries, one per line")
    p.add_argument(
        "--input-format",
        choices=INPUT_FORMATS,
        default="hdf5",
        help="hdf5: the released files; exr: renderer EXRs (see pipelines/hypersim/paths.py)",
    )
    p.add_argument(
        "--resolution",
        default=None,
        metavar="WxH",
        help="stored image size, e.g. 512x384 (one int: square); not given: as rendered",
    )
    p.add_argument("--image-codec", choices=("jpeg", "png"), default="jpeg", help="colour image encoding")
    p.add_argument(
        "--jpeg-quality", dest="image_quality", type=int, default=95, metavar="Q", help="JPEG quality (1..100)"
    )
    p.add_argument("--no-depth", action="store_true", help="do not store per-pixel depth")
    p.add_argument(
        "--min-instance-pixels",
        type=int,
        default=100,
        help="drop (and count) instance masks smaller than this at the stored resolution",
    )
    p.add_argument(
        "--exclude-categories",
        nargs="+",
        default=[],
        help="NYU40 names or ids to leave out; 'stuff' = wall, floor, ceiling",
    )
    p.add_argument("--scenes-per-shard", type=int, default=4, help="Hypersim scenes per output shard")
    return p


def parse_resolution(text: str | None) -> tuple[int, int] | None:
    """``--resolution`` (kept a string in the arguments, so build fingerprints stay as before)."""
    if text is None:
        return None
    try:
        return parse_size(text)
    except argparse.ArgumentTypeError as exc:
        raise UslError(f"--resolution {exc}") from None


def parse_categories(tokens: list[str], spec: dict) -> tuple[int, ...]:
    by_name = {c["name"].lower(): int(c["id"]) for c in spec["categories"]}
    ids = set()
    for token in tokens:
        names = STUFF if token.lower() == "stuff" else (token.lower(),)
        for name in names:
            if name.isdigit() and int(name) in by_name.values():
                ids.add(int(name))
            elif name in by_name:
                ids.add(by_name[name])
            else:
                raise UslError(f"--exclude-categories: {token!r} is not a Hypersim category name or id")
    return tuple(sorted(ids))


def _sha256(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    from .convert import ConvertOptions, build_trajectory, single_threaded_worker  # torch: after parsing
    from .plan import PlanConfig, discover_scenes, parse_blacklist, plan_shards

    try:
        build = build_options_from_args(args)
        spec = load_dataset_spec("hypersim")
        if args.frame_stride < 1 or args.scenes_per_shard < 1 or args.min_instance_pixels < 0:
            raise UslError("--stride and --scenes-per-shard must be >= 1, --min-instance-pixels >= 0")
        if not 1 <= args.image_quality <= 100:
            raise UslError(f"--jpeg-quality {args.image_quality}: must lie in 1..100")
        options = ConvertOptions(
            args.input_format,
            parse_resolution(args.resolution),
            args.image_codec,
            args.image_quality,
            args.min_instance_pixels,
            parse_categories(args.exclude_categories, spec),
            not args.no_depth,
        )
        config = PlanConfig(
            tuple(args.splits),
            tuple(args.cameras),
            args.frame_stride,
            parse_blacklist(args.blacklist, args.blacklist_file),
            args.scenes_per_shard,
        )
        scenes = discover_scenes([Path(s) for s in args.scenes])
        plans, notes = plan_shards(
            scenes,
            read_split_csv(args.split_csv),
            read_camera_csv(args.camera_csv),
            options,
            config,
            args.split_csv,
            args.camera_csv,
        )
        for note in notes:
            print(f"{COMMAND}: not converted: {note}", file=sys.stderr)
        if not plans:
            raise UslError("nothing to convert: no scene folder has a frame left after the split and filters")
        fingerprint = {
            **fingerprint_from_args(args),
            "scenes": {k: str(v) for k, v in scenes.items()},
            "blacklist": sorted(config.blacklist),
            "split_csv_sha256": _sha256(args.split_csv),
            "camera_csv_sha256": _sha256(args.camera_csv),
        }
        summary = run_build(
            build,
            spec,
            fingerprint,
            plans,
            build_trajectory,
            creator_from_args(COMMAND, args),
            worker_initializer=single_threaded_worker,
        )
        print(f"{COMMAND}: {summary.describe()}")
        if summary.manifest_written:
            print(describe_dataset(args.out, load_manifest(args.out)))
    except UslError as exc:
        print(f"{COMMAND}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
