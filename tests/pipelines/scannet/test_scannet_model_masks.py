"""``--masks model``: usl-convert-scannet segments a .sens scan itself, once per build."""

from __future__ import annotations

import json

import pytest

from data_specs import load_dataset_spec
from pipelines.scannet.cli import main
from pipelines.scannet.model_masks import segments_dir
from tests.model.detectron2_fixtures import POINTREND, write_random_checkpoint
from tests.pipelines.scannet.synthetic_scan import SyntheticScan, write_sens
from usl.model.segmenter import InstanceSegmenter
from usl.records import RecordsDataset
from usl.records.validate import validate_dataset

SCENE = "scene0003_00"
STRIDE = 4


@pytest.fixture(scope="module")
def weights(tmp_path_factory):
    """Random PointRend weights that find things (a few in ScanNet's categories) in the synthetic frames."""
    path = tmp_path_factory.mktemp("weights") / "pointrend.pkl"
    write_random_checkpoint(path, POINTREND, seed=1, background_bias=6.0)
    return path


@pytest.fixture(scope="module")
def scans(tmp_path_factory):
    root = tmp_path_factory.mktemp("scannet_model")
    scan = SyntheticScan(num_frames=24)
    (root / "scans" / SCENE).mkdir(parents=True)
    write_sens(root / "scans" / SCENE / f"{SCENE}.sens", scan, list(scan.frames()))
    (root / "splits").mkdir()
    (root / "splits" / "scannetv2_train.txt").write_text(f"{SCENE}\n")
    return root


def convert(scans, out, weights, *extra: str) -> int:
    return main(
        [
            "--out", str(out), "--quiet", "--scans-root", str(scans / "scans"), "--splits-dir", str(scans / "splits"),
            "--splits", "train", "--stride", str(STRIDE), "--resolution", "48x36", "--masks", "model",
            "--weights", str(weights), "--device", "cpu", "--segment-size", "160", "266", "--min-score", "0.1",
            "--min-track-frames", "2", "--iou-threshold", "0.05", "--match-across-categories", *extra,
        ]
    )  # fmt: skip


class CountingSegmenter:
    """Counts the frames the segmenter sees (the build runs inline with --workers 1)."""

    def __init__(self, monkeypatch):
        self.frames = 0
        original = InstanceSegmenter.__call__

        def counted(segmenter, images):
            self.frames += len(images)
            return original(segmenter, images)

        monkeypatch.setattr(InstanceSegmenter, "__call__", counted)


def test_model_masks_convert_a_scan_and_a_resumed_build_never_segments_it_again(
    scans, tmp_path, weights, monkeypatch, capsys
):
    counter = CountingSegmenter(monkeypatch)
    out = tmp_path / "scannet"
    assert convert(scans, out, weights) == 0, capsys.readouterr().err
    assert counter.frames == len(range(0, 24, STRIDE))
    assert validate_dataset(out) == []

    cached = json.loads((segments_dir(out) / f"{SCENE}.json").read_text())
    assert sorted(int(f) for f in cached["frames"]) == list(range(0, 24, STRIDE))
    detections = [d for found in cached["frames"].values() for d in found]
    kept = {c["coco_id"] for c in load_dataset_spec("scannet")["categories"]}
    assert detections and all(d["category_id"] in kept and d["score"] >= 0.1 for d in detections)

    rows = RecordsDataset(out, "train").read_scene(SCENE, columns=["view_id", "instances"])
    assert rows and all(row["view_id"] % STRIDE == 0 for row in rows)
    categories = {inst["category_id"] for row in rows for inst in row["instances"]}
    assert categories <= {c["id"] for c in load_dataset_spec("scannet")["categories"]}
    before = {p.name: p.read_bytes() for p in out.rglob("*.parquet")}

    # An interrupted build: the shard is unfinished, its scan's detections are cached.
    for marker in (out / ".build").glob("train*.json"):
        marker.unlink()
    (out / "manifest.json").unlink()
    assert convert(scans, out, weights) == 0
    assert counter.frames == len(range(0, 24, STRIDE))  # nothing segmented again
    assert {p.name: p.read_bytes() for p in out.rglob("*.parquet")} == before


def test_model_masks_need_weights_that_exist(scans, tmp_path, capsys):
    assert convert(scans, tmp_path / "a", tmp_path / "missing.pkl") == 2
    assert "missing.pkl: no such file" in capsys.readouterr().err
    (tmp_path / "bad.pkl").write_bytes(b"not a pickle")
    assert convert(scans, tmp_path / "b", tmp_path / "bad.pkl", "--no-skip-bad-scenes") == 2
    assert "bad.pkl" in capsys.readouterr().err


@pytest.mark.slow  # a local Ray instance whose workers each load the 240 MB weights: minutes on a small machine
def test_model_masks_under_ray_write_what_a_local_build_writes(scans, tmp_path, weights, local_ray):
    assert convert(scans, tmp_path / "ray", weights, "--executor", "ray") == 0
    assert convert(scans, tmp_path / "local", weights) == 0
    assert shard_bytes(tmp_path / "ray") == shard_bytes(tmp_path / "local")
    cached = [(tmp_path / run / ".build" / "segments" / f"{SCENE}.json").read_text() for run in ("ray", "local")]
    assert cached[0] == cached[1]


def shard_bytes(root):
    return {p.relative_to(root): p.read_bytes() for p in sorted(root.rglob("*.parquet")) if ".build" not in p.parts}
