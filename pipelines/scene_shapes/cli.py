"""``usl-build-scene-shapes``: build the Scene-Shapes records (paper Sec. 4.1, Appendix B): pairs of
chairs, sofas and tables on a floor, seen from an orbit of cameras, with RGB, depth, instance masks
and 3D meshes.

Defaults reproduce the paper's size: 4,000 shapes, 3,600 scenes x 24 views = 86,400 images of
512x512, 80/10/10 splits with disjoint models and scenes.

    usl-build-scene-shapes --out data/scene_shapes --workers 8          # the paper's size
    usl-build-scene-shapes --out data/small --num-scenes 60 --num-models 60 --resolution 128 --views 8 --heights 2
    usl-build-scene-shapes --out data/shapenet --mesh-root /data/ShapeNetCore --category-map synsets.yaml
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
from usl.cli.common import make_parser, resolution
from usl.errors import UslError

from .layout import PlacementConfig, RigConfig
from .mesh_root import SCALE_MODES, UP_AXES, MeshNormalisation, discover_models, dump_category_map, load_category_map
from .render import BACKGROUNDS, check_offscreen_rendering
from .shapes import CATEGORIES, GENERATOR_VERSION, ModelRef, procedural_refs

COMMAND = "usl-build-scene-shapes"
EPILOG = (
    "World frame: the ground frame of camera 0 (origin on the floor below it, +Y up, +Z its\n"
    "horizontal viewing direction), metres; objects stand at X in [-0.4, 0.4], Z in [1.5, 1.9].\n"
    "view_id = height_index * azimuths + azimuth_index; view 0 is camera 0."
)


def parser() -> argparse.ArgumentParser:
    rig = RigConfig()
    common = build_common_options(
        seed="drives splits, layouts, appearance and the procedural shape models (other seeds: other models)"
    )
    p = make_parser(COMMAND, __doc__, parents=[common], epilog=EPILOG)
    add_build_arguments(p)
    p.add_argument("--num-scenes", type=int, default=3600, help="scenes over all splits")
    p.add_argument(
        "--num-models", type=int, default=4000, help="procedural models over all categories (ignored with --mesh-root)"
    )
    p.add_argument("--azimuths", type=int, default=rig.azimuths, help="camera azimuths per height")
    p.add_argument("--heights", type=int, default=rig.heights, help="camera heights, evenly spaced in --height-range")
    p.add_argument(
        "--views", type=int, default=None, help="views per scene; sets --azimuths to views / heights (must divide)"
    )
    p.add_argument(
        "--height-range",
        type=float,
        nargs=2,
        default=rig.height_range,
        metavar=("LOW", "HIGH"),
        help="camera heights above the floor, metres",
    )
    placement = PlacementConfig()
    p.add_argument(
        "--x-range",
        type=float,
        nargs=2,
        default=placement.x_range,
        metavar=("LOW", "HIGH"),
        help="object centres' X in camera 0's ground frame, metres (paper: -0.4 0.4)",
    )
    p.add_argument(
        "--z-range",
        type=float,
        nargs=2,
        default=placement.z_range,
        metavar=("NEAR", "FAR"),
        help="object centres' Z (distance ahead of camera 0), metres (paper: 1.5 1.9); "
        "the cameras orbit the middle of this range",
    )
    p.add_argument(
        "--resolution", type=square_size, default=rig.resolution, metavar="N|NxN", help="image size in pixels (square)"
    )
    p.add_argument(
        "--fov-deg",
        type=float,
        default=rig.fov_deg,
        help="field of view, degrees (70 keeps ~87%% of metric-size objects wholly in frame)",
    )
    p.add_argument(
        "--background",
        choices=BACKGROUNDS,
        default="floor",
        help="floor: a randomly coloured ground plane under a random sky colour; plain: colour only",
    )
    p.add_argument(
        "--image-codec",
        choices=("png", "jpeg"),
        default="jpeg",
        help="jpeg (quality 95) decodes ~2.4x faster than png at 512^2, which bounds training read "
        "throughput; png is lossless",
    )
    p.add_argument("--scenes-per-shard", type=int, default=64, help="scenes per Parquet shard (~130 MB of PNGs at 512)")
    p.add_argument(
        "--mesh-root",
        type=Path,
        default=None,
        help="use your meshes instead of procedural ones: <root>/<category folder>/.../*.obj|glb|ply|off",
    )
    p.add_argument(
        "--category-map",
        type=Path,
        default=None,
        help="YAML/JSON mapping --mesh-root folder names (e.g. ShapeNet synsets) to chair/sofa/table",
    )
    p.add_argument("--up-axis", choices=UP_AXES, default="+y", help="up axis of the --mesh-root meshes")
    p.add_argument(
        "--mesh-scale",
        choices=SCALE_MODES,
        default="category",
        help="category: scale each mesh to its category's typical bounding-box diagonal "
        "(chair 1.15, sofa 2.2, table 1.6 m); none: meshes are already in metres",
    )
    p.add_argument(
        "--skip-bad-meshes",
        action="store_true",
        help="leave out scenes whose mesh cannot be read, recording them in the manifest, "
        "instead of stopping with an error",
    )
    return p


def square_size(text: str) -> int:
    """``--resolution`` in the shared ``WxH``-or-one-int syntax; Scene-Shapes images are square
    (kept an int so build fingerprints stay as before)."""
    width, height = resolution(text)
    if width != height:
        raise argparse.ArgumentTypeError(f"{text!r}: Scene-Shapes images are square; give one size, e.g. 512")
    return width


def _rig(args: argparse.Namespace) -> RigConfig:
    azimuths = args.azimuths
    if args.views is not None:
        if args.views < 1 or args.views % args.heights:
            raise UslError(f"--views {args.views} is not a positive multiple of --heights {args.heights}")
        azimuths = args.views // args.heights
    if azimuths < 1 or args.heights < 1 or args.resolution < 8 or not 1.0 <= args.fov_deg < 170.0:
        raise UslError("need --azimuths >= 1, --heights >= 1, --resolution >= 8 and 1 <= --fov-deg < 170")
    low, high = args.height_range
    if not 0.0 < low <= high:
        raise UslError(f"--height-range {low} {high}: heights must be positive and ascending")
    return RigConfig(
        azimuths=azimuths,
        heights=args.heights,
        height_range=(low, high),
        fov_deg=args.fov_deg,
        resolution=args.resolution,
    )


def _placement(args: argparse.Namespace) -> PlacementConfig:
    (x0, x1), (z0, z1) = args.x_range, args.z_range
    if not (x0 <= x1 and 0.0 < z0 <= z1):
        raise UslError(f"--x-range {x0} {x1} / --z-range {z0} {z1}: need ascending ranges and Z > 0")
    return PlacementConfig(x_range=(x0, x1), z_range=(z0, z1))


def _models(args: argparse.Namespace) -> tuple[list[ModelRef], MeshNormalisation | None, dict]:
    """The model pool, how to normalise it, and what of it belongs in the fingerprint."""
    if args.mesh_root is None:
        if args.category_map is not None:
            raise UslError("--category-map needs --mesh-root")
        # a seed's own model range is in the fingerprint from seed 1 on (seed 0's is the first one, as
        # before seeds had ranges, so its builds resume)
        pool = {"model_pool": "per_seed"} if args.seed else {}
        return procedural_refs(args.num_models, args.seed), None, {"generator_version": GENERATOR_VERSION, **pool}
    if args.category_map is None:
        raise UslError("--mesh-root needs --category-map (folder name -> chair/sofa/table)")
    category_map = load_category_map(args.category_map)
    refs, unmapped = discover_models(args.mesh_root, category_map, empty_is_error=not args.skip_bad_meshes)
    if unmapped:
        print(f"{COMMAND}: not in the category map, not used: {', '.join(unmapped)}", file=sys.stderr)
    listing = "\n".join(f"{r.source_id}\t{Path(r.path).stat().st_size}" for r in refs)
    normalisation = MeshNormalisation(args.up_axis, args.mesh_scale, tuple(sorted(category_map.diagonals.items())))
    return (
        refs,
        normalisation,
        {
            "category_map_content": dump_category_map(category_map),
            "mesh_listing_sha256": hashlib.sha256(listing.encode()).hexdigest(),
        },
    )


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    from .plan import PlanConfig, plan_shards  # torch: after parsing, so --help is fast
    from .scene import SceneConfig, build_scene

    try:
        options = build_options_from_args(args)
        spec = load_dataset_spec("scene_shapes")
        category_ids = {c["name"]: int(c["id"]) for c in spec["categories"]}
        if set(category_ids) != set(CATEGORIES):
            raise UslError(f"data_specs/scene_shapes.yaml lists {sorted(category_ids)}, expected {list(CATEGORIES)}")
        if args.num_scenes < 1 or args.scenes_per_shard < 1:
            raise UslError("--num-scenes and --scenes-per-shard must be >= 1")
        refs, normalisation, model_fingerprint = _models(args)
        scene_config = SceneConfig(
            _rig(args),
            tuple(sorted(category_ids.items())),
            args.background,
            args.image_codec,
            normalisation,
            args.skip_bad_meshes,
        )
        fractions = tuple((name, float(f)) for name, f in spec["splits"].items())
        plans = plan_shards(
            refs,
            PlanConfig(args.num_scenes, args.seed, fractions, args.scenes_per_shard, _placement(args)),
            scene_config,
        )
        fingerprint = {**fingerprint_from_args(args), **model_fingerprint}
        check_offscreen_rendering(scene_config.rig.resolution)
        summary = run_build(options, spec, fingerprint, plans, build_scene, creator_from_args(COMMAND, args))
    except UslError as exc:
        print(f"{COMMAND}: error: {exc}", file=sys.stderr)
        return 2
    print(f"{COMMAND}: {summary.describe()}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
