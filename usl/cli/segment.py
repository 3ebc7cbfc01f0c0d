"""``usl-segment``: COCO instance segmentation of image files with pretrained weights, no detectron2 needed.

    usl-segment frames/*.jpg --weights model_final_edd263.pkl --out results.json     # PointRend R50-FPN
    usl-segment photo.png --weights maskrcnn_resnet50_fpn_coco-bf2d0c1e.pth --out r.json --device cuda

The weights file decides the network: detectron2's PointRend (``pointrend_rcnn_R_50_FPN_3x_coco``) or
Mask R-CNN R50-FPN ``.pkl`` from its model zoo, or torchvision's ``maskrcnn_resnet50_fpn`` COCO
``.pth``. Inference follows detectron2's ``DefaultPredictor`` (shortest edge resized to 800, longest
at most 1333, bilinear; scores above 0.05; 100 detections per image at most).

The output is a COCO results JSON list as detectron2's ``COCOEvaluator`` writes it: per detection
``image_id`` (the image's position on the command line, from 0), ``file_name`` (as given),
``category_id`` (a COCO id), ``bbox`` ([x, y, width, height] in pixels), ``score`` and
``segmentation`` (compressed RLE at the image's own size).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

from usl.cli.common import common_options, make_parser, resolve_device

COMMAND = "usl-segment"


def parser() -> argparse.ArgumentParser:
    common = common_options(
        out="COCO results JSON file to write",
        out_required=True,
        device="where the segmenter runs (auto: cuda when available)",
        quiet="no progress bar",
    )
    p = make_parser(COMMAND, __doc__, parents=[common])
    p.add_argument("images", nargs="+", help="input image file(s)")
    p.add_argument("--weights", required=True, type=Path, help="detectron2 .pkl or torchvision .pth weights file")
    p.add_argument("--batch-size", type=int, default=2, help="images per forward pass")
    test = p.add_argument_group("inference (detectron2's defaults)")
    test.add_argument("--min-size", type=int, default=800, help="shortest image edge after resizing")
    test.add_argument("--max-size", type=int, default=1333, help="longest image edge after resizing, at most")
    test.add_argument("--score-threshold", type=float, default=0.05, help="keep detections scoring above this")
    test.add_argument("--max-detections", type=int, default=100, help="detections per image, at most")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = parser().parse_args(argv)
    from usl.errors import UslError
    from usl.inference.segment import coco_results, segment_files  # torch loads here
    from usl.model.pretrained import WeightsError
    from usl.model.segmenter import InstanceSegmenter, SegmenterConfig
    from usl.records.atomic import write_json_atomic

    try:
        missing = [p for p in args.images if not Path(p).is_file()]
        if missing:  # checked before the weights load
            raise UslError(
                f"image {missing[0]} does not exist" + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else "")
            )
        if min(args.min_size, args.max_size, args.max_detections, args.batch_size) < 1:
            raise UslError("--min-size, --max-size, --max-detections and --batch-size must be >= 1")
        cfg = SegmenterConfig(args.min_size, args.max_size, args.score_threshold, args.max_detections)
        try:
            segmenter = InstanceSegmenter.from_weights(args.weights, cfg, resolve_device(args.device))
        except WeightsError as exc:
            raise UslError(str(exc)) from None
        results, count = [], 0
        for index, path, segmentation in segment_files(segmenter, args.images, args.batch_size, not args.quiet):
            results += coco_results(segmentation, index, str(path))
            count += 1
        args.out.parent.mkdir(parents=True, exist_ok=True)
        write_json_atomic(args.out, results, indent=None)
    except UslError as exc:
        print(f"{COMMAND}: error: {exc}", file=sys.stderr)
        return 2
    if not args.quiet:
        print(f"{COMMAND}: {len(results)} detections in {count} image(s) -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
