"""The COCO export as pycocotools reads it, and with what detectron2's load_coco_json requires."""

import contextlib
import io
import json

import cv2
import numpy as np
import pytest
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

from usl.cli.records import main as records_cli
from usl.records import RecordsDataset, decode_mask


@pytest.fixture(scope="module")
def export(fake_build, tmp_path_factory):
    out = tmp_path_factory.mktemp("coco")
    assert (
        records_cli(
            [
                "export-coco",
                str(fake_build),
                "--split",
                "train",
                "--out",
                str(out / "train.json"),
                "--images-dir",
                str(out / "images"),
            ]
        )
        == 0
    )
    with contextlib.redirect_stdout(io.StringIO()):
        coco = COCO(str(out / "train.json"))
    return coco, out


def test_ground_truth_against_itself_has_ap_one(export):
    coco, _ = export
    for iou_type in ("bbox", "segm"):
        detections = [{**a, "score": 1.0} for a in coco.dataset["annotations"]]
        with contextlib.redirect_stdout(io.StringIO()):
            evaluator = COCOeval(coco, coco.loadRes(detections), iou_type)
            evaluator.evaluate()
            evaluator.accumulate()
            evaluator.summarize()
        assert evaluator.stats[0] == pytest.approx(1.0) and evaluator.stats[1] == pytest.approx(1.0)


def test_masks_boxes_and_ids_match_the_records(export, fake_build):
    coco, _ = export
    records = RecordsDataset(fake_build, "train")
    rows = [row for scene in records.scene_ids for row in records.read_scene(scene)]
    assert len(coco.imgs) == len(rows) == 7
    for image_id, row in zip(sorted(coco.imgs), rows, strict=True):
        image = coco.imgs[image_id]
        assert (image["scene_id"], image["view_id"], image["height"], image["width"]) == (
            row["scene_id"],
            row["view_id"],
            row["height"],
            row["width"],
        )
        anns = coco.imgToAnns[image_id]
        assert [a["instance_id"] for a in anns] == [i["instance_id"] for i in row["instances"]]
        for ann, inst in zip(anns, row["instances"], strict=True):
            np.testing.assert_array_equal(coco.annToMask(ann).astype(bool), decode_mask(inst["mask"]))
            x0, y0, x1, y1 = inst["box_xyxy"]
            assert ann["bbox"] == pytest.approx([x0, y0, x1 - x0, y1 - y0]) and ann["area"] == inst["area"]
            assert coco.cats[ann["category_id"]]["name"] == ["disc", "square"][inst["category_id"] - 1]


def test_what_detectron2_load_coco_json_reads(export):
    """detectron2 joins image_root with file_name, takes height/width/id from images, asserts unique
    annotation ids, matching image_id and no "ignore", and keeps RLE dicts with str counts."""
    coco, out = export
    data = json.loads((out / "train.json").read_text())
    ann_ids = [a["id"] for a in data["annotations"]]
    assert len(set(ann_ids)) == len(ann_ids) and all("ignore" not in a for a in data["annotations"])
    assert {a["image_id"] for a in data["annotations"]} <= {i["id"] for i in data["images"]}
    assert "s%2F1/000003.png" in {i["file_name"] for i in data["images"]}
    for image in data["images"]:
        pixels = cv2.imread(str(out / "images" / image["file_name"]))
        assert pixels is not None and pixels.shape[:2] == (image["height"], image["width"])
    assert all(isinstance(a["segmentation"]["counts"], str) and a["iscrowd"] == 0 for a in data["annotations"])
    assert sorted(c["id"] for c in data["categories"]) == [1, 2]
