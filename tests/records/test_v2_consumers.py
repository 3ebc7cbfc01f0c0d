"""Real consumers read v2 folders as they are: pandas, pyarrow.dataset, Hugging Face datasets."""

import json

import numpy as np
import pandas as pd
import pyarrow.dataset as pads
import pytest

from usl.records import RecordsDataset, decode_image, decode_mask

datasets = pytest.importorskip("datasets")


def manifest(root):
    return json.loads((root / "manifest.json").read_text())


def test_pandas_and_pyarrow_dataset_read_one_table_per_folder(fake_v2):
    splits = manifest(fake_v2)["splits"]
    frames = pd.read_parquet(fake_v2 / "frames" / "train")
    assert len(frames) == splits["train"]["num_frames"] == 7 and frames["image"].notna().all()
    assert list(frames.columns) == [
        "scene_id",
        "view_id",
        "image",
        "height",
        "width",
        "K",
        "cam_to_world",
        "depth",
        "instances",
    ]
    objects = pads.dataset(fake_v2 / "objects" / "train", format="parquet")
    assert objects.count_rows() == splits["train"]["num_objects"] == 4
    schema = pads.dataset(fake_v2 / "frames" / "val", format="parquet").schema
    assert b"OpenCV" in schema.field("cam_to_world").metadata[b"doc"]
    assert b"XYWH" in schema.field("instances").type.value_type.field("box_xyxy").metadata[b"doc"]


def test_hugging_face_loads_frames_by_default_with_images_and_class_names(fake_v2, tmp_path, monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_DATASETS_OFFLINE", "1")
    frames = datasets.load_dataset(str(fake_v2), split="train", cache_dir=str(tmp_path))
    ours = RecordsDataset(fake_v2, "train")
    assert frames.num_rows == 7 and frames["scene_id"] == [s for s in ours.scene_ids for _ in range(ours.num_views(s))]
    want = ours.read_scene("s/1")[2]
    got = frames[3 + 2]
    np.testing.assert_array_equal(np.asarray(got["image"].convert("RGB")), decode_image(want["image"]))
    label = frames.features["instances"].feature["category_id"]
    assert [label.int2str(i["category_id"]) for i in got["instances"]] == ["disc", "square"]
    np.testing.assert_array_equal(decode_mask(got["instances"][1]["mask"]), decode_mask(want["instances"][1]["mask"]))
    assert got["instances"][0]["box_xyxy"] == pytest.approx(want["instances"][0]["box_xyxy"])
    objects = datasets.load_dataset(str(fake_v2), "objects", split="val", cache_dir=str(tmp_path))
    assert objects.num_rows == 2 and objects.features["category_id"].names[1:] == ["disc", "square"]
