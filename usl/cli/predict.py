"""``usl-predict``: 3D objects from single images with a trained model.

    usl-predict photo.jpg --checkpoint runs/hypersim --fov 60                 # -> predictions/photo.glb
    usl-predict IMG_0042.jpg --checkpoint runs/hypersim --fov auto            # field of view from EXIF
    usl-predict *.png --checkpoint run/ --K intrinsics.txt --formats glb,html,obj --out preds/

For each image: ``<name>.glb`` with one mesh per detected object (node ``<index>_<category>``, its
category name, the dataset's category id and score in the node's ``extras``), a camera matching the
input view (the full K in its ``extras``) and the image as a textured plane behind the objects;
``--formats`` adds ``html`` (a 3D viewer that opens at the input camera; offline, one file),
``obj`` and ``ply`` (objects only); and ``<name>_overlay.png``, the meshes rendered over the image
with boxes and scores. Only glTF (and the page) keeps each object's category and score: an OBJ keeps
the objects apart as named groups with one material each (trimesh's load_scene and Open3D's
read_triangle_model load them as separate meshes; Open3D's read_triangle_mesh merges them, as it
does a GLB's), a PLY is one merged mesh with a vertex colour per object.

``--fov auto`` reads EXIF FocalLengthIn35mmFilm (matched on the diagonal, as the EXIF standard
does); without it, it assumes 60 degrees and says so.

Axes: glTF's, +Y up with the camera looking down -Z (``diag(1, -1, -1)`` applied to the OpenCV
camera frame of docs/design.md §2), metres; ``--axes opencv`` keeps x right, y down, z forward. ``K``
follows docs/design.md §2 (pixel centres at +0.5); a K from an OpenCV calibration (integer pixel
centres) needs ``--opencv-k``.
"""

from __future__ import annotations

import argparse
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from usl.cli.common import common_options, make_parser, resolve_device, warning_lines
from usl.inference.field_of_view import FieldOfViewWarning
from usl.inference.formats import FORMATS

if TYPE_CHECKING:
    from usl.inference.predict import ImageResult

COMMAND = "usl-predict"


def field_of_view(text: str) -> float | str:
    """``auto`` or a number of degrees."""
    if text == "auto":
        return text
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected degrees or 'auto', got {text!r}") from None


def parser() -> argparse.ArgumentParser:
    common = common_options(
        out="output folder",
        out_default="predictions",
        device="where the model runs (auto: cuda when available)",
        quiet="print nothing but errors",
    )
    p = make_parser(COMMAND, __doc__, parents=[common])
    p.add_argument("images", nargs="+", help="input image file(s)")
    p.add_argument("--checkpoint", required=True, help="checkpoint file or training run folder")
    camera = p.add_mutually_exclusive_group(required=True)
    camera.add_argument("--K", dest="k_file", help="3x3 intrinsics for the images' resolution (text or JSON)")
    camera.add_argument(
        "--fov",
        type=field_of_view,
        help="horizontal field of view in degrees (centred principal point), or 'auto' (EXIF, else 60)",
    )
    p.add_argument("--opencv-k", action="store_true", help="K puts pixel centres at integers (OpenCV): shift by +0.5")
    p.add_argument("--formats", default="glb", help=f"comma-separated output formats from {', '.join(FORMATS)}")
    p.add_argument("--score-threshold", type=float, default=0.5, help="keep detections scoring at least this")
    p.add_argument(
        "--axes",
        default="gltf",
        choices=("gltf", "opencv", "opengl"),
        help="axes of the written files: gltf (+Y up, looking down -Z; 'opengl' is the same) or opencv",
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = parser().parse_args(argv)
    from usl.errors import UslError

    try:
        with warning_lines(COMMAND):  # an assumed field of view, a saved setting ignored: one line each
            warnings.simplefilter("always", FieldOfViewWarning)  # a line for each image it applies to
            results = _predict(args)
    except UslError as exc:
        print(f"{COMMAND}: error: {exc}", file=sys.stderr)
        return 2
    for image, result in results.items():
        if args.quiet:
            continue
        if result.num_objects == 0:
            best = "no detection at all" if result.best_score is None else f"best score {result.best_score:.2f}"
            print(
                f"{image}: no detection scores >= {args.score_threshold:g} ({best}); wrote only "
                f"{', '.join(str(f) for f in result.files)} (lower --score-threshold to see more)"
            )
        else:
            print(f"{image}: {result.num_objects} object(s): {', '.join(str(f) for f in result.files)}")
    return 0


def _predict(args: argparse.Namespace) -> dict[str, ImageResult]:
    """Load the model, predict every image and write its files: what each image gave."""
    from usl.errors import UslError
    from usl.inference.predict import model_detector, predict_images, read_intrinsics  # torch loads here
    from usl.records.output_folder import output_folder

    K = read_intrinsics(args.k_file) if args.k_file else None
    formats = [f.strip() for f in args.formats.split(",") if f.strip()]
    missing = [p for p in args.images if not Path(p).is_file()]
    if missing:  # checked before the model loads; predict_images decodes them all before any work
        raise UslError(
            f"image {missing[0]} does not exist" + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else "")
        )
    detect, categories = model_detector(args.checkpoint, resolve_device(args.device))
    with output_folder(Path(args.out), COMMAND, "the files of the images done so far are kept"):
        return predict_images(
            detect,
            args.images,
            args.out,
            categories,
            K,
            args.fov,
            formats,
            args.score_threshold,
            "gltf" if args.axes == "opengl" else args.axes,
            args.opencv_k,
        )


if __name__ == "__main__":
    sys.exit(main())
