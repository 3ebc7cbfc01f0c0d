"""``--masks model``: usl-convert-captures segments a capture's frames itself, once per build."""

from __future__ import annotations

import json

import pytest

from data_specs import load_dataset_spec
from pipelines.captures.cli import main
from pipelines.scannet.model_masks import segments_dir
from tests.pipelines.scannet.test_scannet_model_masks import CountingSegmenter, weights  # noqa: F401 (fixture)
from usl.records.validate import validate_dataset

STRIDE = 8


def convert(folder, out, weights) -> int:  # noqa: F811 (the fixture's value)
    return main(
        [
            str(folder), "--out", str(out), "--quiet", "--stride", str(STRIDE), "--masks", "model",
            "--weights", str(weights), "--device", "cpu", "--segment-size", "120", "160", "--min-score", "0.1",
            "--min-track-frames", "2", "--iou-threshold", "0.05", "--match-across-categories",
        ]
    )  # fmt: skip


@pytest.mark.slow  # PointRend on the CPU: ~20 s; the segmenter source itself runs in the ScanNet tests
def test_model_masks_segment_a_capture_once(capture, tmp_path, weights, monkeypatch, capsys):  # noqa: F811
    counter = CountingSegmenter(monkeypatch)
    out = tmp_path / "records"
    assert convert(capture.root / "nerfstudio", out, weights) == 0, capsys.readouterr().err
    assert counter.frames == len(range(0, 24, STRIDE))
    assert validate_dataset(out) == []
    cached = json.loads((segments_dir(out) / "nerfstudio.json").read_text())
    kept = {c["coco_id"] for c in load_dataset_spec("captures")["categories"]}
    assert all(d["category_id"] in kept for found in cached["frames"].values() for d in found)
    for marker in (out / ".build").glob("train*.json"):  # an interrupted build: segmented frames are cached
        marker.unlink()
    (out / "manifest.json").unlink()
    assert convert(capture.root / "nerfstudio", out, weights) == 0
    assert counter.frames == len(range(0, 24, STRIDE))
