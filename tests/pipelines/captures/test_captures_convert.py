"""End to end: ``usl-convert-captures`` on a rendered capture in each input format, checked against the
renderer's truth (poses, K, depth, visible masks), the record validator and the manifest's provenance."""

from __future__ import annotations

import json
import shutil
from collections import defaultdict

import numpy as np
import pytest

from pipelines.captures.cli import main
from pipelines.scannet.grid import resample_nearest
from usl.records import RecordsDataset, decode_depth, decode_mask, load_manifest
from usl.records.validate import validate_dataset

CATEGORIES = {"dining table": "table", "chair": "chair"}


def convert(folder, out, *extra: str) -> int:
    return main([str(folder), "--out", str(out), "--quiet", *extra])


def rotation_angle(R: np.ndarray) -> float:
    return float(np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def read_frames(out) -> list[dict]:
    dataset = RecordsDataset(out, "train")
    (scene,) = dataset.scene_ids
    return dataset.read_scene(scene)


def check_poses(frames: list[dict], truth, max_degrees: float, max_metres: float | None) -> None:
    """Every pair's relative pose against the truth (the records' world frame is the source's)."""
    poses = {f["view_id"]: np.asarray(f["cam_to_world"], float).reshape(4, 4) for f in frames}
    views = sorted(poses)
    for a in views:
        for b in views[1:]:
            got = np.linalg.inv(poses[a]) @ poses[b]
            want = np.linalg.inv(truth.cam_to_world[a]) @ truth.cam_to_world[b]
            assert rotation_angle(got[:3, :3].T @ want[:3, :3]) <= max_degrees, (a, b)
            if max_metres is not None:
                assert np.abs(got[:3, 3] - want[:3, 3]).max() <= max_metres, (a, b)


def check_objects(frames: list[dict], truth, categories: dict[int, str]) -> None:
    """Exactly the two true objects, right categories, >= 12 frames each, every mask on its true object."""
    by_instance: dict[int, list[str]] = defaultdict(list)
    names = {}
    for frame in frames:
        height, width = frame["height"], frame["width"]
        for inst in frame["instances"]:
            mask = decode_mask(inst["mask"]).astype(bool)
            ious = {}
            for obj, true_mask in truth.masks[frame["view_id"]].items():
                true_mask = resample_nearest(true_mask, height, width)
                ious[obj] = (mask & true_mask).sum() / max((mask | true_mask).sum(), 1)
            best = max(ious, key=ious.get)
            assert ious[best] >= 0.9, (frame["view_id"], ious)
            by_instance[inst["instance_id"]].append(best)
            names[inst["instance_id"]] = CATEGORIES[categories[inst["category_id"]]]
    assert len(by_instance) == 2
    for instance, objects in by_instance.items():
        assert set(objects) == {names[instance]}
        assert len(objects) >= 12
    assert sorted(names.values()) == ["chair", "table"]


@pytest.mark.parametrize("form", ["nerfstudio", "colmap_text", "colmap_binary"])
def test_capture_formats_match_the_truth(capture, colmap_binary, form, tmp_path):
    truth = capture.truth
    out = tmp_path / "records"
    assert convert(capture.root / form, out, "--resolution", "native") == 0
    assert validate_dataset(out) == []
    manifest = load_manifest(out)
    frames = read_frames(out)
    assert sorted(f["view_id"] for f in frames) == list(range(len(truth.images)))
    check_poses(frames, truth, 0.1, 1e-3)
    for frame in frames:
        np.testing.assert_allclose(np.asarray(frame["K"]).reshape(3, 3), truth.K, atol=1e-9)
        depth = decode_depth(frame["depth"])
        true_depth = truth.depth[frame["view_id"]]
        valid = (true_depth > 0) & np.isfinite(depth) & (depth > 0)
        assert valid.mean() > 0.9
        assert np.abs(depth[valid] - true_depth[valid]).max() <= 0.01
    categories = {c["id"]: c["name"] for c in manifest["categories"]}
    check_objects(frames, truth, categories)
    (about,) = manifest["provenance"].values()
    assert about["association"] == "mask IoU, depth-warped"
    if form == "nerfstudio":
        assert about["pose_source"] == "transforms.json" and about["scale"] == 1.0
    else:
        assert about["scale_origin"].startswith("depth maps") and about["scale"] == pytest.approx(0.37, rel=1e-3)
    assert "scale_origin" in json.dumps(manifest["provenance"])
    assert "### Scenes" in (out / "README.md").read_text()


def test_output_resolution_scales_K_and_masks(capture, tmp_path):
    truth = capture.truth
    out = tmp_path / "records"
    assert convert(capture.root / "nerfstudio", out, "--max-side", "80", "--no-warp") == 0
    frames = read_frames(out)
    assert (frames[0]["width"], frames[0]["height"]) == (80, 60)
    np.testing.assert_allclose(np.asarray(frames[0]["K"]).reshape(3, 3), np.diag([0.5, 0.5, 1.0]) @ truth.K)
    check_objects(frames, truth, {c["id"]: c["name"] for c in load_manifest(out)["categories"]})
    (about,) = load_manifest(out)["provenance"].values()
    assert about["association"] == "mask IoU in place"


def test_resume_keeps_the_finished_build(capture, tmp_path):
    out = tmp_path / "records"
    assert convert(capture.root / "nerfstudio", out) == 0
    before = (out / "manifest.json").read_text()
    assert convert(capture.root / "nerfstudio", out, "--workers", "2") == 0
    assert json.loads((out / "manifest.json").read_text())["splits"] == json.loads(before)["splits"]


def test_a_folder_of_captures_with_one_held_out(capture, colmap_binary, tmp_path):
    out = tmp_path / "records"
    assert convert(capture.root, out, "--val", "colmap_text", "--max-side", "80") == 0
    splits = load_manifest(out)["splits"]
    assert splits["val"]["num_scenes"] == 1 and splits["train"]["num_scenes"] == 2
    assert RecordsDataset(out, "val").scene_ids == ["colmap_text"]
    assert convert(capture.root, tmp_path / "other", "--val", "nowhere") == 2


def test_scale_from_the_option_or_the_prior(capture, tmp_path):
    """--scale multiplies the poses; a COLMAP model without depth gets the documented prior."""
    truth = capture.truth
    assert convert(capture.root / "nerfstudio", tmp_path / "scaled", "--scale", "2", "--max-side", "80") == 0
    (about,) = load_manifest(tmp_path / "scaled")["provenance"].values()
    assert (about["scale"], about["scale_origin"]) == (2.0, "--scale")
    frames = read_frames(tmp_path / "scaled")
    got = np.asarray(frames[-1]["cam_to_world"], float).reshape(4, 4)[:3, 3]
    np.testing.assert_allclose(got, 2 * truth.cam_to_world[frames[-1]["view_id"]][:3, 3], atol=1e-6)

    folder = tmp_path / "no_depth"
    shutil.copytree(capture.root / "colmap_text", folder)
    shutil.rmtree(folder / "depth")
    assert convert(folder, tmp_path / "prior", "--max-side", "80") == 0
    (about,) = load_manifest(tmp_path / "prior")["provenance"].values()
    assert about["scale_origin"].startswith("prior") and not about["depth"]
    assert about["association"] == "mask IoU in place"
    depths = np.concatenate([d[d > 0] for d in truth.depth])  # the sparse points sample these surfaces
    assert about["scale"] == pytest.approx(0.37 * 2.0 / np.median(depths), rel=0.1)
    check_objects(
        read_frames(tmp_path / "prior"),
        truth,
        {c["id"]: c["name"] for c in load_manifest(tmp_path / "prior")["categories"]},
    )
