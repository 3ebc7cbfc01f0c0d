"""Shared synthetic ScanNet inputs: one scan written as .sens and as exported folders, with detections
and ScanNet label images, plus the official split files. Built once per test run."""

from __future__ import annotations

import json
from types import SimpleNamespace

import pytest

from tests.pipelines.scannet.synthetic_scan import (
    SyntheticScan,
    write_detections,
    write_exported,
    write_label_map,
    write_labels,
    write_sens,
)

SENS_SCENE = "scene0001_00"
EXPORTED_SCENE = "scene0002_00"
LOST = (5, 50, 51)


@pytest.fixture(scope="session")
def synthetic(tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    root = tmp_path_factory.mktemp("scannet")
    scan = SyntheticScan(num_frames=120, lost_frames=LOST)
    frames = list(scan.frames())
    scans = root / "scans"
    sens_dir, exported_dir = scans / SENS_SCENE, scans / EXPORTED_SCENE
    sens_dir.mkdir(parents=True)
    write_sens(sens_dir / f"{SENS_SCENE}.sens", scan, frames)
    write_labels(sens_dir, scan, frames)
    write_exported(exported_dir, scan, frames)
    write_labels(exported_dir, scan, frames)
    write_label_map(root / "labels.tsv")
    write_detections(root / "results_a.json", root / "images_a.json", SENS_SCENE, scan, frames, seed=1)
    write_detections(
        root / "results_b.json", root / "images_b.json", EXPORTED_SCENE, scan, frames, seed=2, first_image_id=1000
    )
    images = [
        *json.loads((root / "images_a.json").read_text())["images"],
        *json.loads((root / "images_b.json").read_text())["images"],
    ]
    (root / "images.json").write_text(json.dumps({"images": images}))  # one images file, as one detectron2 run
    splits = root / "splits"
    splits.mkdir()
    (splits / "scannetv2_train.txt").write_text(f"{SENS_SCENE}\n")
    (splits / "scannetv2_val.txt").write_text(f"{EXPORTED_SCENE}\n")
    return SimpleNamespace(
        root=root,
        scan=scan,
        frames=frames,
        scans=scans,
        splits=splits,
        lost=set(LOST),
        sens=sens_dir / f"{SENS_SCENE}.sens",
        exported=exported_dir,
        labels=root / "labels.tsv",
        results=[root / "results_a.json", root / "results_b.json"],
        images=root / "images.json",
    )
