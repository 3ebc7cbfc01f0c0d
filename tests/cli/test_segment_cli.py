"""usl-segment writes detectron2's COCO results for image files (checked against the recorded oracle)."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pycocotools.mask as mask_util

from data_specs import coco_category_ids
from tests.model.detectron2_fixtures import MASK_RCNN, write_test_images
from tests.model.test_segmenter_oracle import ORACLE
from usl.cli.segment import main


def test_usl_segment_writes_what_detectron2_predicts(tmp_path, detectron2_weights):
    run = next(r for r in ORACLE["runs"] if r["model"] == MASK_RCNN)
    weights = detectron2_weights[MASK_RCNN][0]
    image = next(p for p in write_test_images(tmp_path) if p.name == "scannet.png")
    twin = tmp_path / "twin.png"
    shutil.copy(image, twin)
    out = tmp_path / "out" / "results.json"
    argv = [str(image), str(twin), "--weights", str(weights), "--out", str(out), "--batch-size", "2", "--quiet"]
    assert main([*argv, "--min-size", str(run["min_size"]), "--max-size", str(run["max_size"])]) == 0
    results = json.loads(out.read_text())
    first = [r for r in results if r["image_id"] == 0]
    second = [r for r in results if r["image_id"] == 1]
    assert {r["file_name"] for r in first} == {str(image)} and {r["file_name"] for r in second} == {str(twin)}
    # one batch of two same-size images gives each what one image alone gives
    assert [r["segmentation"] for r in first] == [r["segmentation"] for r in second]
    theirs = run["images"]["scannet.png"]
    assert len(first) == len(theirs)
    by_score = sorted(first, key=lambda r: -r["score"])
    for ours, oracle in zip(by_score, sorted(theirs, key=lambda d: -d["score"]), strict=True):
        assert ours["category_id"] == coco_category_ids()[oracle["class"]]
        x0, y0, x1, y1 = oracle["box"]
        np.testing.assert_allclose(ours["bbox"], [x0, y0, x1 - x0, y1 - y0], atol=0.05)
        assert abs(ours["score"] - oracle["score"]) < 1e-4
        assert ours["segmentation"]["size"] == [480, 640]
        rle = {"size": [480, 640], "counts": oracle["mask"]}
        assert mask_util.iou([ours["segmentation"]], [rle], [False])[0, 0] >= 0.99


def test_usl_segment_names_a_bad_weights_file(tmp_path, capsys):
    image = write_test_images(tmp_path)[0]
    (tmp_path / "weights.pkl").write_bytes(b"not a pickle")
    code = main([str(image), "--weights", str(tmp_path / "weights.pkl"), "--out", str(tmp_path / "r.json")])
    assert code == 2
    assert "weights.pkl" in capsys.readouterr().err
    assert main([str(tmp_path / "missing.png"), "--weights", "w.pkl", "--out", str(tmp_path / "r.json")]) == 2
    assert "missing.png does not exist" in capsys.readouterr().err
