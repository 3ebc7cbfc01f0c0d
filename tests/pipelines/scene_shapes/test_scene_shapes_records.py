"""Built records against independent oracles: masks and depth vs. each stored mesh re-rendered
alone from the stored camera, back-projected depth vs. the mesh surface, splits, determinism."""

import json

import numpy as np
import pytest

from pipelines.scene_shapes.cli import main
from tests.pipelines.scene_shapes.scene_shapes_oracle import backproject, distance_to_mesh, iou, render_depth_alone
from usl.records import RecordsDataset, decode_depth, decode_mask, frame_K, frame_pose, load_manifest, object_mesh
from usl.records.schema import file_schema_version
from usl.records.validate import validate_dataset

SPLITS = ("train", "val", "test")


def scenes(root):
    for split in SPLITS:
        data = RecordsDataset(root, split)
        for scene_id in data.scene_ids:
            yield data.read_scene(scene_id), data.read_objects(scene_id)


def test_masks_follow_the_nearest_ground_truth_surface(tiny_dataset):
    checked_unoccluded = checked_occluded = 0
    ious = []
    for frames, objects in scenes(tiny_dataset):
        meshes = {o["instance_id"]: object_mesh(o) for o in objects}
        for frame in frames:
            K, pose, h, w = frame_K(frame), frame_pose(frame), frame["height"], frame["width"]
            alone = {i: render_depth_alone(v, f, K, pose, h, w) for i, (v, f) in meshes.items()}
            stored = {inst["instance_id"]: inst for inst in frame["instances"]}
            depth = decode_depth(frame["depth"])
            for i, own in alone.items():
                silhouette = own > 0
                nearer_other = np.zeros_like(silhouette)
                for j, other in alone.items():
                    if j != i:
                        nearer_other |= (other > 0) & (other < own)
                expected = silhouette & ~nearer_other
                if i not in stored:
                    assert expected.sum() <= 2, "an object visible in the oracle render is missing"
                    continue
                mask = decode_mask(stored[i]["mask"])
                assert (mask & ~silhouette).sum() <= 1, "mask pixels outside the object's own render"
                ious.append(iou(mask, expected))
                assert ious[-1] >= 0.95
                if not nearer_other[silhouette].any():
                    assert iou(mask, silhouette) >= 0.95
                    checked_unoccluded += 1
                else:
                    checked_occluded += 1
                valid = mask & expected
                error = np.abs(depth[valid] - own[valid])
                assert np.quantile(error, 0.99) <= 0.003, "stored depth differs from the mesh's depth"
                assert stored[i]["depth_min"] == pytest.approx(np.nanmin(depth[mask]), abs=6e-4)  # PNG is in mm
    assert checked_unoccluded >= 5 and checked_occluded >= 20  # the paper's close pairs occlude a lot
    assert np.mean(ious) >= 0.99


def test_backprojected_depth_lies_on_the_stored_meshes_and_floor(tiny_dataset):
    """Pure numpy/trimesh oracle of K, cam_to_world and depth units: pixels of instance k back-project
    onto mesh k; other pixels with depth back-project onto the floor plane y = 0."""
    rng = np.random.default_rng(0)
    for frames, objects in list(scenes(tiny_dataset))[:4]:
        meshes = {o["instance_id"]: object_mesh(o) for o in objects}
        for frame in frames[::2]:
            K, pose, depth = frame_K(frame), frame_pose(frame), decode_depth(frame["depth"])
            covered = np.zeros(depth.shape, bool)
            for inst in frame["instances"]:
                mask = decode_mask(inst["mask"])
                covered |= mask
                rows, cols = np.nonzero(mask)
                pick = rng.choice(len(rows), size=min(60, len(rows)), replace=False)
                points = backproject(depth, K, pose, rows[pick], cols[pick])
                vertices, faces = meshes[inst["instance_id"]]
                distances = distance_to_mesh(points, vertices.astype(np.float64), faces)
                assert np.quantile(distances, 0.9) < 0.004 and distances.max() < 0.05
            rows, cols = np.nonzero(~covered & np.isfinite(depth))
            floor = backproject(depth, K, pose, rows, cols)
            assert len(rows) > 0.05 * depth.size
            assert np.abs(floor[:, 1]).max() < 0.01


def test_cameras_are_rigid_and_share_the_stored_intrinsics(tiny_dataset):
    for frames, _ in scenes(tiny_dataset):
        first = frame_pose(frames[0])
        assert first[:3, 3][[0, 2]] == pytest.approx([0.0, 0.0], abs=1e-9), "world origin is below camera 0"
        assert first[1, 2] < 0 and first[0, 2] == pytest.approx(0.0, abs=1e-9), "camera 0 looks along +Z, down"
        for frame in frames:
            pose, K = frame_pose(frame), frame_K(frame)
            np.testing.assert_allclose(pose[:3, :3].T @ pose[:3, :3], np.eye(3), atol=1e-9)
            assert np.linalg.det(pose[:3, :3]) == pytest.approx(1.0)
            assert pose[1, 1] < 0, "image down is world down (+Y up)"
            np.testing.assert_allclose(K, frame_K(frames[0]))
            assert K[0, 2] == K[1, 2] == frame["width"] / 2


def test_dataset_passes_the_record_validator(tiny_dataset):
    assert validate_dataset(tiny_dataset) == []
    splits = sorted(load_manifest(tiny_dataset)["splits"])
    assert load_manifest(tiny_dataset)["schema_version"] == 3 and (tiny_dataset / "README.md").exists()
    assert {file_schema_version(p) for p in (tiny_dataset / "frames").rglob("*.parquet")} == {3}  # depth an Image
    assert sorted(p.name for p in (tiny_dataset / "frames").iterdir()) == splits
    assert sorted(p.name for p in (tiny_dataset / "objects").iterdir()) == splits


def test_splits_are_disjoint_in_models_and_scenes(tiny_dataset):
    manifest = load_manifest(tiny_dataset)
    assert {k: v["num_scenes"] for k, v in manifest["splits"].items()} == {"train": 8, "val": 1, "test": 1}
    models, scene_ids = {}, {}
    for split in SPLITS:
        data = RecordsDataset(tiny_dataset, split)
        scene_ids[split] = set(data.scene_ids)
        models[split] = {o["source_id"] for s in data.scene_ids for o in data.read_objects(s)}
        for s in data.scene_ids:
            assert [o["instance_id"] for o in data.read_objects(s)] == [1, 2]
    for a in SPLITS:
        for b in SPLITS:
            if a < b:
                assert not models[a] & models[b] and not scene_ids[a] & scene_ids[b]
    category_ids = {c["name"]: c["id"] for c in manifest["categories"]}
    for split in SPLITS:
        data = RecordsDataset(tiny_dataset, split)
        for s in data.scene_ids:
            for o in data.read_objects(s):
                assert o["category_id"] == category_ids[o["source_id"].split("/")[1]]


def _shard_checksums(root):
    manifest = load_manifest(root)
    return {
        (split, shard["index"]): (shard["frames"]["sha256"], (shard["objects"] or {}).get("sha256"))
        for split, entry in manifest["splits"].items()
        for shard in entry["shards"]
    }


def test_output_is_identical_for_one_and_two_workers(tmp_path):
    args = [
        "--num-scenes",
        "6",
        "--num-models",
        "15",
        "--resolution",
        "48",
        "--azimuths",
        "2",
        "--heights",
        "1",
        "--scenes-per-shard",
        "2",
        "--seed",
        "11",
        "--quiet",
    ]
    assert main(["--out", str(tmp_path / "w1"), "--workers", "1", *args]) == 0
    assert main(["--out", str(tmp_path / "w2"), "--workers", "2", *args]) == 0
    assert _shard_checksums(tmp_path / "w1") == _shard_checksums(tmp_path / "w2")


def test_refuses_an_output_folder_holding_another_build(tiny_dataset, capsys):
    build = json.loads((tiny_dataset / ".build" / "build.json").read_text())
    assert build["fingerprint"]["generator_version"] >= 1
    assert main(["--out", str(tiny_dataset), "--num-scenes", "10", "--seed", "6", "--quiet"]) == 2
    assert str(tiny_dataset) in capsys.readouterr().err


def test_a_build_with_another_seed_shares_no_shape_model(tiny_dataset, tmp_path):
    """Held-out builds (another --seed) hold out shapes as well as scenes."""
    other = tmp_path / "seed6"
    small = ["--num-scenes", "3", "--num-models", "30", "--resolution", "32", "--azimuths", "1", "--heights", "1"]
    assert main(["--out", str(other), *small, "--seed", "6", "--quiet"]) == 0
    assert _source_ids(other) and _source_ids(tiny_dataset)
    assert not _source_ids(other) & _source_ids(tiny_dataset)
    build = json.loads((other / ".build" / "build.json").read_text())
    assert build["fingerprint"]["model_pool"] == "per_seed"


def _source_ids(root):
    """Every shape model a build's objects name, over all splits (read back from the records)."""
    return {
        o["source_id"]
        for split in SPLITS
        for data in [RecordsDataset(root, split)]
        for s in data.scene_ids
        for o in data.read_objects(s)
    }
