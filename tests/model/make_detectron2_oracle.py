"""Write fixtures/detectron2_oracle.json.gz: detectron2's DefaultPredictor on the test images.

Run with detectron2's public source on the path (never installed into the project's environment;
its C++ extension is not needed for inference on the CPU), e.g.::

    PYTHONPATH=.:detectron2:detectron2/projects/PointRend python tests/model/make_detectron2_oracle.py

Both models get the seeded random weights of :mod:`detectron2_fixtures`, written in the model zoo's
pickle layout and read with detectron2's own checkpointer. The tests replay the outputs without
detectron2 (tests/model/test_segmenter_oracle.py).
"""

from __future__ import annotations

import argparse
import gzip
import json
import tempfile
from pathlib import Path

import cv2
import numpy as np
import pycocotools.mask as mask_util
import torch
from detectron2.config import get_cfg
from detectron2.engine import DefaultPredictor
from point_rend import add_pointrend_config

from tests.model.detectron2_fixtures import (
    FIXTURES,
    MASK_RCNN,
    ORACLE_SEED,
    POINTREND,
    checksum,
    write_random_checkpoint,
    write_test_images,
)

CONFIGS = {
    POINTREND: "projects/PointRend/configs/InstanceSegmentation/pointrend_rcnn_R_50_FPN_3x_coco.yaml",
    MASK_RCNN: "configs/COCO-InstanceSegmentation/mask_rcnn_R_50_FPN_3x.yaml",
}
# (model, shortest edge, longest edge): a fast size for every test run, and detectron2's defaults.
RUNS = ((POINTREND, 320, 533), (MASK_RCNN, 320, 533), (POINTREND, 800, 1333))


def predictions(predictor: DefaultPredictor, path: Path) -> list[dict]:
    instances = predictor(cv2.imread(str(path)))["instances"].to("cpu")
    masks = np.asfortranarray(instances.pred_masks.numpy().transpose(1, 2, 0).astype(np.uint8))
    rles = mask_util.encode(masks) if len(instances) else []
    return [
        {"class": int(c), "score": float(s), "box": [float(v) for v in b], "mask": rle["counts"].decode()}
        for c, s, b, rle in zip(
            instances.pred_classes.tolist(),
            instances.scores.tolist(),
            instances.pred_boxes.tensor.tolist(),
            rles,
            strict=True,
        )
    ]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--detectron2", type=Path, default=Path("detectron2"), help="detectron2's source folder")
    parser.add_argument("--out", type=Path, default=FIXTURES / "detectron2_oracle.json.gz")
    args = parser.parse_args()
    torch.set_num_threads(2)
    runs = []
    sums = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        images = write_test_images(folder)
        for model, min_size, max_size in RUNS:
            weights = folder / f"{model}.pkl"
            sums[model] = checksum(write_random_checkpoint(weights, model, ORACLE_SEED))
            cfg = get_cfg()
            add_pointrend_config(cfg)
            cfg.merge_from_file(str(args.detectron2 / CONFIGS[model]))
            cfg.MODEL.DEVICE = "cpu"
            cfg.MODEL.WEIGHTS = str(weights)
            cfg.INPUT.MIN_SIZE_TEST, cfg.INPUT.MAX_SIZE_TEST = min_size, max_size
            predictor = DefaultPredictor(cfg)
            outputs = {path.name: predictions(predictor, path) for path in images}
            runs.append({"model": model, "min_size": min_size, "max_size": max_size, "images": outputs})
            print(model, min_size, {name: len(found) for name, found in outputs.items()}, flush=True)
    payload = {"seed": ORACLE_SEED, "checksums": sums, "runs": runs}
    with gzip.open(args.out, "wt") as stream:
        json.dump(payload, stream)
    print(f"wrote {args.out} ({args.out.stat().st_size} bytes)")


if __name__ == "__main__":
    main()
