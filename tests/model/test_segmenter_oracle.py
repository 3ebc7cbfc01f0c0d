"""InstanceSegmenter against detectron2's DefaultPredictor (outputs recorded by make_detectron2_oracle.py).

Same random weights (seeded, model zoo layout), same images: the detections must agree as sets
(class, score, box), boxes to float tolerance and masks at IoU >= 0.99. Detections that only one
side keeps may differ only at the 100-per-image cut, where random weights leave near-ties.
"""

from __future__ import annotations

import gzip
import json

import cv2
import numpy as np
import pycocotools.mask as mask_util
import pytest

from tests.model.detectron2_fixtures import (
    FIXTURES,
    MASK_RCNN,
    POINTREND,
    checksum,
    write_random_checkpoint,
    write_test_images,
)
from data_specs import coco_category_ids
from usl.model.segmenter import InstanceSegmenter, SegmenterConfig

ORACLE = json.loads(gzip.open(FIXTURES / "detectron2_oracle.json.gz", "rt").read())
BOX_TOLERANCE = 0.05  # pixels of the original image
SCORE_TOLERANCE = 1e-4
MIN_MASK_IOU = 0.99


@pytest.fixture(scope="module")
def images(tmp_path_factory):
    folder = tmp_path_factory.mktemp("images")
    return {path.name: cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB) for path in write_test_images(folder)}


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    folder = tmp_path_factory.mktemp("weights")
    paths = {}
    for model in (POINTREND, MASK_RCNN):
        path = folder / f"{model}.pkl"
        assert checksum(write_random_checkpoint(path, model, ORACLE["seed"])) == pytest.approx(
            ORACLE["checksums"][model], rel=1e-9
        ), "numpy drew other random weights than when the oracle was recorded"
        paths[model] = path
    return paths


def match(ours, theirs, height: int, width: int) -> dict:
    """Pair detections of the same class and score; return the pairing's statistics."""
    cut = min([d["score"] for d in theirs] + [float(s) for s in ours.scores], default=1.0)
    free = set(range(len(ours)))
    pairs, unmatched = [], []
    for oracle in theirs:
        category = coco_category_ids()[oracle["class"]]
        candidates = [
            i
            for i in free
            if ours.category_ids[i] == category and abs(float(ours.scores[i]) - oracle["score"]) < SCORE_TOLERANCE
        ]
        if not candidates:
            unmatched.append(oracle["score"])
            continue
        best = min(candidates, key=lambda i: np.abs(ours.boxes[i] - oracle["box"]).max())
        free.remove(best)
        rle = {"size": [height, width], "counts": oracle["mask"]}
        mask = mask_util.decode(rle).astype(bool)
        union = np.logical_or(mask, ours.masks[best]).sum()
        iou = np.logical_and(mask, ours.masks[best]).sum() / union if union else 1.0
        pairs.append((float(np.abs(ours.boxes[best] - oracle["box"]).max()), float(iou)))
    unmatched += [float(ours.scores[i]) for i in free]
    return {"pairs": pairs, "unmatched": unmatched, "cut": cut}


def check_run(run, images, weights):
    cfg = SegmenterConfig(min_size=run["min_size"], max_size=run["max_size"])
    segmenter = InstanceSegmenter.from_weights(weights[run["model"]], cfg)
    names = sorted(run["images"])
    results = segmenter([images[name] for name in names])
    for name, ours in zip(names, results):
        theirs = run["images"][name]
        height, width = images[name].shape[:2]
        stats = match(ours, theirs, height, width)
        assert len(stats["pairs"]) >= 0.9 * len(theirs) > 0, (name, len(stats["pairs"]), len(theirs))
        # only near-ties at the per-image cut may go unpaired
        assert all(score < stats["cut"] + 2e-3 for score in stats["unmatched"]), (name, stats["unmatched"])
        box_errors, ious = zip(*stats["pairs"])
        assert max(box_errors) < BOX_TOLERANCE, (name, max(box_errors))
        assert min(ious) >= MIN_MASK_IOU, (name, min(ious))


FAST_RUNS = [run for run in ORACLE["runs"] if run["min_size"] < 800]
DEFAULT_RUNS = [run for run in ORACLE["runs"] if run["min_size"] == 800]


@pytest.mark.parametrize("run", FAST_RUNS, ids=lambda r: f"{r['model']}-{r['min_size']}")
def test_segmenter_reproduces_detectron2(run, images, weights):
    check_run(run, images, weights)


@pytest.mark.slow
@pytest.mark.parametrize("run", DEFAULT_RUNS, ids=lambda r: f"{r['model']}-{r['min_size']}")
def test_segmenter_reproduces_detectron2_at_its_default_size(run, images, weights):
    check_run(run, images, weights)
