"""Real consumers read dataset folders as they are: pandas, pyarrow.dataset, Hugging Face datasets."""

import json

import cv2
import numpy as np
import pandas as pd
import pyarrow.dataset as pads
import pyarrow.parquet as pq
import pytest

from tests.records.old_writer import write_old_copy
from usl.records import RecordsDataset, decode_depth, decode_image, decode_mask
from usl.records.card import dataset_card
from usl.records.schema import HF_METADATA_KEY, legacy_hf_features
from usl.records.shards import sha256_file
from usl.records.validate import validate_dataset

datasets = pytest.importorskip("datasets")


def manifest(root):
    return json.loads((root / "manifest.json").read_text())


def test_pandas_and_pyarrow_dataset_read_one_table_per_folder(fake_build):
    splits = manifest(fake_build)["splits"]
    frames = pd.read_parquet(fake_build / "frames" / "train")
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
    objects = pads.dataset(fake_build / "objects" / "train", format="parquet")
    assert objects.count_rows() == splits["train"]["num_objects"] == 4
    schema = pads.dataset(fake_build / "frames" / "val", format="parquet").schema
    assert b"OpenCV" in schema.field("cam_to_world").metadata[b"doc"]
    assert b"XYWH" in schema.field("instances").type.value_type.field("box_xyxy").metadata[b"doc"]


def test_hugging_face_loads_frames_by_default_with_images_and_the_datasets_category_ids(
    fake_build, tmp_path, monkeypatch
):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_DATASETS_OFFLINE", "1")
    frames = datasets.load_dataset(str(fake_build), split="train", cache_dir=str(tmp_path))
    ours = RecordsDataset(fake_build, "train")
    assert frames.num_rows == 7 and frames["scene_id"] == [s for s in ours.scene_ids for _ in range(ours.num_views(s))]
    want = ours.read_scene("s/1")[2]
    got = frames[3 + 2]
    np.testing.assert_array_equal(np.asarray(got["image"].convert("RGB")), decode_image(want["image"]))
    # one id space: the manifest's ids (1 disc, 2 square), the same as records and COCO; no placeholder class
    assert frames.features["instances"].feature["category_id"] == datasets.Value("int64")
    names = {c["id"]: c["name"] for c in manifest(fake_build)["categories"]}
    assert [names[i["category_id"]] for i in got["instances"]] == ["disc", "square"]
    assert "__unused" not in json.dumps(frames.features.to_dict())
    np.testing.assert_array_equal(decode_mask(got["instances"][1]["mask"]), decode_mask(want["instances"][1]["mask"]))
    assert got["instances"][0]["box_xyxy"] == pytest.approx(want["instances"][0]["box_xyxy"])
    objects = datasets.load_dataset(str(fake_build), "objects", split="val", cache_dir=str(tmp_path))
    assert objects.num_rows == 2 and objects.features["category_id"] == datasets.Value("int64")
    assert {names[i] for i in objects["category_id"]} <= {"disc", "square"}


def test_datasets_with_the_earlier_class_label_features_validate_and_load(fake_build, tmp_path, monkeypatch):
    """v2 folders written when category_id was a ClassLabel with ``__unused_0__``: same Arrow data, both
    ``usl-records validate`` and Hugging Face accept them, and the ClassLabel names the same ids."""
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_DATASETS_OFFLINE", "1")
    root = write_old_copy(fake_build, tmp_path / "legacy", 2)
    data = manifest(root)
    for entry in data["splits"].values():
        for shard in entry["shards"]:
            for table in ("frames", "objects"):
                if shard[table]:
                    _rewrite_features(root, shard[table], legacy_hf_features(table, data["categories"]))
    (root / "manifest.json").write_text(json.dumps(data))
    assert validate_dataset(root) == []
    frames = datasets.load_dataset(str(root), split="train", cache_dir=str(tmp_path / "cache"))
    label = frames.features["instances"].feature["category_id"]
    assert label.names == ["__unused_0__", "disc", "square"]
    assert [label.int2str(i["category_id"]) for i in frames[5]["instances"]] == ["disc", "square"]
    # anything else in the features metadata is stale, for usl-records validate
    _rewrite_features(root, data["splits"]["val"]["shards"][0]["frames"], {"scene_id": {"dtype": "int64"}})
    (root / "manifest.json").write_text(json.dumps(data))
    assert any("features metadata missing or stale" in p for p in validate_dataset(root))


def test_hugging_face_decodes_depth_to_the_records_millimetres_losslessly(fake_build, tmp_path, monkeypatch):
    """Schema v3 ``depth`` is an Image: Hugging Face hands out a 16-bit PIL image whose pixels are the
    stored millimetres (0 = unknown), for every value the builders write up to 65535, and None where
    a view has no depth; pandas hands out the same struct, its bytes the same PNG."""
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_DATASETS_OFFLINE", "1")
    frames = datasets.load_dataset(str(fake_build), split="train", cache_dir=str(tmp_path))
    assert frames.features["depth"] == datasets.Image()
    ours = RecordsDataset(fake_build, "train")
    records = [row for s in ours.scene_ids for row in ours.read_scene(s)]
    table = pd.read_parquet(fake_build / "frames" / "train")
    assert len(records) == frames.num_rows == len(table) == 7
    for record, got, cell in zip(records, frames, table["depth"], strict=True):
        if record["depth"] is None:  # scene s/1 view 2
            assert got["depth"] is None and cell is None
            continue
        assert got["depth"].mode == "I;16" and got["depth"].size == (record["width"], record["height"])
        mm = np.asarray(got["depth"])
        metres = decode_depth(record["depth"])
        np.testing.assert_array_equal(mm, cv2.imdecode(np.frombuffer(cell["bytes"], np.uint8), cv2.IMREAD_UNCHANGED))
        np.testing.assert_array_equal(np.isnan(metres), mm == 0)
        np.testing.assert_array_equal(mm[mm > 0] / np.float32(1000), metres[mm > 0])
        assert mm[0, :6].tolist() == [0, 1, 32767, 32768, 40000, 65535]  # fake_scenes writes these
    assert sum(r["depth"] is None for r in records) == 1


def _rewrite_features(root, info, features):
    """Replace one shard's Hugging Face features, its manifest size and checksum following."""
    path = root / info["file"]
    table = pq.read_table(path)
    metadata = {**table.schema.metadata, HF_METADATA_KEY: json.dumps({"info": {"features": features}}).encode()}
    pq.write_table(table.replace_schema_metadata(metadata), path)
    info["bytes"], info["sha256"] = path.stat().st_size, sha256_file(path)


def test_dataset_card_reads_in_hugging_face_with_licence_tasks_types_and_provenance(fake_build):
    from huggingface_hub import DatasetCard

    data = manifest(fake_build)
    data["name"] = "scene_shapes"  # a dataset usl knows the licence of
    data["creator"] = {
        "command": "usl-build-scene-shapes",
        "argv": ["--out", "data/my set", "--seed", "7"],
        "arguments": {"out": "data/my set", "seed": 7},
        "usl_version": "0.1.0",
    }
    card = DatasetCard(dataset_card(data))
    assert card.data.license == "mit" and "image-to-3d" in card.data.task_categories
    assert card.data.configs[0]["config_name"] == "frames"
    assert "| `instances` | `list<struct>` |" in card.text  # in a code span: not swallowed as an HTML tag
    assert "| 1 | disc |" in card.text and "| 2 | square |" in card.text
    assert "usl-build-scene-shapes --out 'data/my set' --seed 7" in card.text and "Seed: 7" in card.text
    assert DatasetCard(dataset_card(manifest(fake_build))).data.license == "other"  # a spec usl does not know
