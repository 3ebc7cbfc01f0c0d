"""Detections in detectron2's COCO results format: frame mapping, category mapping, RLE checks and
the errors for files that do not fit the scans."""

from __future__ import annotations

import json

import numpy as np
import pytest
from pycocotools import mask as mask_utils

from data_specs import coco_category_ids, load_dataset_spec
from pipelines.scannet.detections_file import (
    DetectionsFileSource,
    frame_of_file_name,
    split_detections,
)
from pipelines.scannet.masks import FrameView, checked_rle
from pipelines.scannet.sens import SensScan
from usl.errors import UslError

SCENE = "scene0001_00"
SPEC_MAPPING = tuple((int(c["coco_id"]), int(c["id"])) for c in load_dataset_spec("scannet")["categories"])


@pytest.mark.parametrize(
    "name, expected",
    [
        ("scene0000_00/color/123.jpg", ("scene0000_00", 123)),
        ("/data/scannet/scene0706_01/exported/color/0.png", ("scene0706_01", 0)),
        ("scene0000_00\\color\\7.JPG", ("scene0000_00", 7)),
        ("scene0000_00_123.jpg", None),
        ("scene0000_00/color/frame-1.jpg", None),
    ],
)
def test_frame_of_file_name(name, expected):
    assert frame_of_file_name(name) == expected


def test_coco_contiguous_ids():
    assert len(coco_category_ids()) == 80
    assert coco_category_ids()[56] == 62 and coco_category_ids()[62] == 72  # detectron2: chair 56, tv 62


def test_detections_reach_their_frames_with_dataset_categories(synthetic, tmp_path):
    split_detections(synthetic.results, synthetic.images, {SCENE}, tmp_path / "cache")
    assert not (tmp_path / "cache" / "scene0002_00.jsonl").exists()  # not asked for
    source = DetectionsFileSource(str(tmp_path / "cache"), SPEC_MAPPING)
    with SensScan(synthetic.sens) as scan:
        masks = source.open_scan(scan)
        coco_to_dataset = dict(SPEC_MAPPING)
        for frame in synthetic.frames[::17]:
            dets = masks.detect(FrameView(frame.index, lambda: None))
            found = {tuple(mask_utils.decode(d.rle).ravel()): d.category_id for d in dets}
            expected = {}
            for box in synthetic.scan.boxes:
                mask = frame.instances == box.instance
                if mask.any():
                    expected[tuple(np.asfortranarray(mask.astype(np.uint8)).ravel())] = coco_to_dataset[box.coco_id]
            assert found == expected


def _one_detection(tmp_path, synthetic, *, image=None, detection=None, contiguous=False):
    """Run one hand-made detection of frame 3 through split + open; returns its detections."""
    mask = np.zeros((72, 96), np.uint8)
    mask[10:20, 30:50] = 1
    rle = mask_utils.encode(np.asfortranarray(mask))
    tmp_path.mkdir(exist_ok=True)
    image = {"id": 7, "file_name": f"{SCENE}/color/3.jpg", "width": 96, "height": 72, **(image or {})}
    det = {
        "image_id": 7,
        "category_id": 62,
        "score": 0.9,
        "bbox": [30, 10, 20, 10],
        "segmentation": {"size": [72, 96], "counts": rle["counts"].decode()},
        **(detection or {}),
    }
    (tmp_path / "images.json").write_text(json.dumps([image]))
    (tmp_path / "results.json").write_text(json.dumps([det]))
    split_detections([tmp_path / "results.json"], tmp_path / "images.json", {SCENE}, tmp_path / "cache")
    with SensScan(synthetic.sens) as scan:
        masks = DetectionsFileSource(str(tmp_path / "cache"), SPEC_MAPPING, contiguous).open_scan(scan)
        return masks.detect(FrameView(3, lambda: None))


def test_hand_made_detection_is_read(tmp_path, synthetic):
    (det,) = _one_detection(tmp_path, synthetic)
    assert det.category_id == 1 and det.score == 0.9 and mask_utils.area(det.rle) == 200
    (det,) = _one_detection(tmp_path / "c", synthetic, detection={"category_id": 56}, contiguous=True)
    assert det.category_id == 1
    assert _one_detection(tmp_path / "p", synthetic, detection={"category_id": 1}) == []  # person: not a category


@pytest.mark.parametrize(
    "image, detection, message",
    [
        (
            {"width": 1296, "height": 968},
            {"segmentation": {"size": [968, 1296], "counts": "X5"}},
            r"results\.json: detections for scene0001_00 are for 1296x968 images, but .*scene0001_00\.sens has 96x72",
        ),
        (
            {},
            {"segmentation": {"size": [72, 95], "counts": "X5"}},
            r"results\.json: image_id 7: malformed mask: .*differs",
        ),
        ({}, {"segmentation": {"size": [72, 96], "counts": "ab!!"}}, r"results\.json: image_id 7: malformed mask"),
        ({}, {"segmentation": {"size": [72, 96], "counts": "X5"}}, r"image_id 7: malformed mask: RLE runs cover"),
        ({}, {"segmentation": [[1.0, 2.0, 3.0, 4.0, 5.0, 6.0]]}, r"image_id 7: malformed mask: .*polygons"),
        ({}, {"category_id": 0}, r"category_id 0 is not a COCO category id \(0-based class indices\?"),
        ({}, {"score": None}, r"image_id 7: score None"),
        ({"file_name": f"{SCENE}/color/999.jpg"}, {}, r"names frame 999 of scene0001_00, which .*sens does not have"),
    ],
)
def test_bad_detections_are_named(tmp_path, synthetic, image, detection, message):
    with pytest.raises(UslError, match=message):
        _one_detection(tmp_path, synthetic, image=image, detection=detection)


def test_detection_of_unknown_image_is_refused(tmp_path, synthetic):
    (tmp_path / "images.json").write_text(
        json.dumps([{"id": 1, "file_name": f"{SCENE}/color/0.jpg", "width": 96, "height": 72}])
    )
    (tmp_path / "results.json").write_text(json.dumps([{"image_id": 2, "category_id": 62, "score": 1.0}]))
    with pytest.raises(UslError, match=r"results\.json: detection 0 refers to image_id 2, which .*images\.json"):
        split_detections([tmp_path / "results.json"], tmp_path / "images.json", {SCENE}, tmp_path / "cache")


def test_images_without_frame_names_are_refused(tmp_path):
    (tmp_path / "images.json").write_text(
        json.dumps({"images": [{"id": 1, "file_name": "img_0001.jpg", "width": 9, "height": 9}]})
    )
    with pytest.raises(UslError, match=r"images\.json: image 1: cannot tell scan and frame"):
        split_detections([], tmp_path / "images.json", {SCENE}, tmp_path / "cache")


def test_checked_rle_accepts_uncompressed_counts_and_matches_pycocotools():
    mask = np.zeros((6, 5), np.uint8)
    mask[1:4, 2:4] = 1
    runs = []  # column-major runs, first one counting zeros
    flat, value, count = mask.ravel(order="F"), 0, 0
    for pixel in flat:
        if pixel != value:
            runs.append(count)
            value, count = pixel, 0
        count += 1
    runs.append(count)
    rle = checked_rle({"size": [6, 5], "counts": runs})
    np.testing.assert_array_equal(mask_utils.decode(rle), mask)
    with pytest.raises(ValueError, match="cover"):
        checked_rle({"size": [6, 5], "counts": runs[:-1]})


def test_scannet_labels_read_from_zips_as_from_folders(synthetic, tmp_path):
    import shutil
    import zipfile

    from pipelines.scannet.scannet_labels import ScanNetLabelsSource

    scan_dir = tmp_path / SCENE
    scan_dir.mkdir()
    shutil.copy(synthetic.sens, scan_dir / synthetic.sens.name)
    for kind in ("instance-filt", "label-filt"):
        with zipfile.ZipFile(scan_dir / f"{SCENE}_2d-{kind}.zip", "w") as archive:
            for index in range(30):
                archive.write(synthetic.sens.parent / kind / f"{index}.png", f"{kind}/{index}.png")
    source = ScanNetLabelsSource(str(synthetic.labels), ((1, "chair"), (2, "couch"), (7, "tv")))
    with SensScan(synthetic.sens) as folders, SensScan(scan_dir / synthetic.sens.name) as zipped:
        a, b = source.open_scan(folders), source.open_scan(zipped)
        for index in (0, 7, 29):
            view = FrameView(index, lambda: None)
            assert a.detect(view) == b.detect(view) and len(a.detect(view)) >= 3
        assert b.detect(FrameView(100, lambda: None)) == []  # frame without label images


def test_masks_of_one_scan_must_share_a_size(synthetic):
    from pipelines.scannet.convert import frame_detections
    from pipelines.scannet.masks import Detection

    class TwoSizes:
        def detect(self, frame):
            shape = (72, 96) if frame.index == 0 else (36, 48)
            return [Detection(1, 0.9, mask_utils.encode(np.asfortranarray(np.ones(shape, np.uint8))))]

    size = [None, None]
    with SensScan(synthetic.sens) as scan:
        assert len(frame_detections(TwoSizes(), scan, 0, 0.5, size)) == 1 and size == [72, 96]
        with pytest.raises(UslError, match=r"scene0001_00\.sens: frame 1: .*must share a size"):
            frame_detections(TwoSizes(), scan, 1, 0.5, size)
