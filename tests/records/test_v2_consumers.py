"""Real consumers read v2 folders as they are: pandas, pyarrow.dataset, Hugging Face datasets."""

import json
import shutil

import numpy as np
import pandas as pd
import pyarrow.dataset as pads
import pyarrow.parquet as pq
import pytest

from usl.records import RecordsDataset, decode_image, decode_mask
from usl.records.card import dataset_card
from usl.records.schema import HF_METADATA_KEY, legacy_hf_features
from usl.records.shards import sha256_file
from usl.records.validate import validate_dataset

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


def test_hugging_face_loads_frames_by_default_with_images_and_the_datasets_category_ids(fake_v2, tmp_path, monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_DATASETS_OFFLINE", "1")
    frames = datasets.load_dataset(str(fake_v2), split="train", cache_dir=str(tmp_path))
    ours = RecordsDataset(fake_v2, "train")
    assert frames.num_rows == 7 and frames["scene_id"] == [s for s in ours.scene_ids for _ in range(ours.num_views(s))]
    want = ours.read_scene("s/1")[2]
    got = frames[3 + 2]
    np.testing.assert_array_equal(np.asarray(got["image"].convert("RGB")), decode_image(want["image"]))
    # one id space: the manifest's ids (1 disc, 2 square), the same as records and COCO; no placeholder class
    assert frames.features["instances"].feature["category_id"] == datasets.Value("int64")
    names = {c["id"]: c["name"] for c in manifest(fake_v2)["categories"]}
    assert [names[i["category_id"]] for i in got["instances"]] == ["disc", "square"]
    assert "__unused" not in json.dumps(frames.features.to_dict())
    np.testing.assert_array_equal(decode_mask(got["instances"][1]["mask"]), decode_mask(want["instances"][1]["mask"]))
    assert got["instances"][0]["box_xyxy"] == pytest.approx(want["instances"][0]["box_xyxy"])
    objects = datasets.load_dataset(str(fake_v2), "objects", split="val", cache_dir=str(tmp_path))
    assert objects.num_rows == 2 and objects.features["category_id"] == datasets.Value("int64")
    assert {names[i] for i in objects["category_id"]} <= {"disc", "square"}


def test_datasets_with_the_earlier_class_label_features_validate_and_load(fake_v2, tmp_path, monkeypatch):
    """v2 folders written when category_id was a ClassLabel with ``__unused_0__``: same Arrow data, both
    ``usl-records validate`` and Hugging Face accept them, and the ClassLabel names the same ids."""
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    monkeypatch.setenv("HF_DATASETS_OFFLINE", "1")
    root = tmp_path / "legacy"
    shutil.copytree(fake_v2, root)
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


def _rewrite_features(root, info, features):
    """Replace one shard's Hugging Face features, its manifest size and checksum following."""
    path = root / info["file"]
    table = pq.read_table(path)
    metadata = {**table.schema.metadata, HF_METADATA_KEY: json.dumps({"info": {"features": features}}).encode()}
    pq.write_table(table.replace_schema_metadata(metadata), path)
    info["bytes"], info["sha256"] = path.stat().st_size, sha256_file(path)


def test_dataset_card_reads_in_hugging_face_with_licence_tasks_types_and_provenance(fake_v2):
    from huggingface_hub import DatasetCard

    data = manifest(fake_v2)
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
    assert DatasetCard(dataset_card(manifest(fake_v2))).data.license == "other"  # a spec usl does not know
