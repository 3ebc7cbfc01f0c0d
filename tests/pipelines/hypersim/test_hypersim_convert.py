"""End-to-end: synthetic Hypersim folders -> records, checked against the ray-cast ground truth."""

import numpy as np
import pytest
import torch

from tests.pipelines.hypersim.hypersim_fixture import render
from tests.pipelines.hypersim.hypersim_inputs import MIN_PIXELS, NAN_PATCH
from usl.geometry.cameras import project, scale_intrinsics, transform_points, unproject
from usl.records import RecordsDataset, decode_depth, decode_image, decode_mask, frame_K, frame_pose, load_manifest
from usl.records.validate import validate_dataset


# Planar depth passes through float16 distances (relative 2^-11) and millimetre PNG (0.5 mm).
def tolerance(distance):
    return 1e-3 * distance + 1e-3


def rows_by_scene(root):
    out = {}
    for split in load_manifest(root)["splits"]:
        ds = RecordsDataset(root, split)
        for scene_id in ds.scene_ids:
            out[scene_id] = ds.read_scene(scene_id)
    return out


def truth_for(inputs, row):
    scene, camera = row["scene_id"].split("/")
    return render(inputs.scenes[scene], camera, row["view_id"], row["width"], row["height"])


def on_one_plane(inputs, row):
    """Output pixels (of a 2x downsampling) whose 4x4 source neighbourhood lies on one face of one
    box: there the converter's inverse-depth interpolation must be exact."""
    scene, camera = row["scene_id"].split("/")
    face = render(inputs.scenes[scene], camera, row["view_id"]).face
    if (row["scene_id"], row["view_id"]) == ("ai_001_001/cam_00", 4):
        face[NAN_PATCH] = -1  # unknown depth in the source
    padded = np.pad(face, 1, mode="edge")
    h, w = row["height"], row["width"]
    blocks = np.stack([padded[dy : dy + 2 * h : 2, dx : dx + 2 * w : 2] for dy in range(4) for dx in range(4)])
    return (blocks == blocks[0]).all(axis=0) & (blocks[0] >= 0)


def pixel_grid(height, width):
    jj, ii = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    return np.stack([jj, ii], axis=-1)


def test_records_are_valid(native, half):
    assert validate_dataset(native) == []
    assert validate_dataset(half) == []


def test_only_included_frames_with_readable_files_are_converted(native):
    rows = rows_by_scene(native)
    assert {k: [r["view_id"] for r in v] for k, v in rows.items()} == {
        "ai_001_001/cam_00": [0, 1, 4, 5],  # 2 flagged, 3 without geometry, 6-7 not downloaded
        "ai_002_001/cam_00": [4, 5],  # 0 bad rotation, 1 truncated, 2 no geometry, 3 wrong shape
    }
    manifest = load_manifest(native)
    assert set(manifest["splits"]) == {"train", "val"}


def test_skips_name_their_reason_and_file(native):
    skips = load_manifest(native)["skips"]
    by_reason = {}
    for s in skips:
        by_reason.setdefault(s["reason"], []).append(s)
    assert [(s["path"], s["count"]) for s in by_reason["official exclusion: CONTENT FLAGGED FOR REMOVAL"]] == [
        ("ai_001_001/cam_00", 1)
    ]
    outside = by_reason["official exclusion: OUTSIDE VIEWING AREA (BAD TRAJECTORY)"]
    assert [(s["path"], s["count"]) for s in outside] == [("ai_001_001/cam_01", 8)]
    missing = sorted(s["path"].split("/")[-1] for s in by_reason["missing depth_meters file"])
    assert missing == ["frame.0003.depth_meters.hdf5", "frame.0006.depth_meters.hdf5", "frame.0007.depth_meters.hdf5"]
    assert by_reason["camera orientation is not a rotation"][0]["path"].endswith(
        "ai_002_001/_detail/cam_00/camera_keyframe_orientations.hdf5"
    )
    assert by_reason["unreadable semantic HDF5 (OSError)"][0]["path"].endswith("frame.0001.semantic.hdf5")
    assert by_reason["no valid geometry in frame"][0]["path"].endswith("frame.0002.depth_meters.hdf5")
    shape = [r for r in by_reason if r.startswith("frame arrays disagree in shape")]
    assert len(shape) == 1 and by_reason[shape[0]][0]["path"].endswith("frame.0003.depth_meters.hdf5")
    assert sum(s["count"] for s in by_reason["instance without an NYU40 label"]) > 0
    (absent,) = by_reason["missing image folder"]
    assert absent["path"].endswith("ai_002_001/images/scene_cam_01_final_hdf5") and absent["count"] == 4
    assert manifest_total(skips) == load_manifest(native)["num_skipped"]


def manifest_total(skips):
    return sum(s["count"] for s in skips)


@pytest.mark.parametrize("records", ["native", "half"])
def test_depth_reprojects_to_the_true_surface(records, inputs, request):
    """unproject(pixel centre, stored depth, stored K) then cam_to_world recovers the ray-cast points."""
    root = request.getfixturevalue(records)
    checked = 0
    for rows in rows_by_scene(root).values():
        for row in rows:
            truth = truth_for(inputs, row)
            depth = decode_depth(row["depth"])
            ok = np.isfinite(depth) & np.isfinite(truth.planar)
            if records == "half":
                ok &= on_one_plane(inputs, row)
            uv = torch.from_numpy(pixel_grid(row["height"], row["width"])[ok])
            K = torch.from_numpy(frame_K(row))
            cam = unproject(uv, torch.from_numpy(depth[ok].astype(np.float64)), K)
            world = transform_points(cam, torch.from_numpy(frame_pose(row))).numpy()
            error = np.linalg.norm(world - truth.points[ok], axis=-1)
            assert (error <= tolerance(truth.distance[ok])).all(), (row["scene_id"], row["view_id"], error.max())
            checked += ok.sum()
    assert checked > 500


def test_true_points_project_to_their_pixel_centres(native, half, inputs):
    """The stored K and pose alone (no depth) map every ray-cast point to the pixel it was cast through."""
    for root in (native, half):
        for rows in rows_by_scene(root).values():
            for row in rows:
                truth = truth_for(inputs, row)
                ok = np.isfinite(truth.planar)
                world_to_cam = torch.linalg.inv(torch.from_numpy(frame_pose(row)))
                cam = transform_points(torch.from_numpy(truth.points[ok]), world_to_cam)
                uv, w = project(cam, torch.from_numpy(frame_K(row)))
                np.testing.assert_allclose(uv.numpy(), pixel_grid(row["height"], row["width"])[ok], atol=1e-6)
                np.testing.assert_allclose(cam[:, 2].numpy(), truth.planar[ok], rtol=1e-9)
                assert (w > 0).all()


def test_half_resolution_K_is_the_scaled_native_K(native, half):
    full, small = rows_by_scene(native), rows_by_scene(half)
    for scene_id in full:
        expected = scale_intrinsics(torch.from_numpy(frame_K(full[scene_id][0])), 0.5, 0.5).numpy()
        np.testing.assert_allclose(frame_K(small[scene_id][0]), expected, rtol=1e-12)
        assert small[scene_id][0]["width"] == 32 and small[scene_id][0]["height"] == 24


def test_nan_depth_patch_is_unknown_not_invented(native, inputs):
    row = next(r for r in rows_by_scene(native)["ai_001_001/cam_00"] if r["view_id"] == 4)
    depth = decode_depth(row["depth"])
    assert np.isnan(depth[NAN_PATCH]).all()
    truth = truth_for(inputs, row)
    outside = np.ones_like(depth, bool)
    outside[NAN_PATCH] = False
    assert (np.isfinite(depth) == np.isfinite(truth.planar))[outside].all()


def expected_categories(inputs, rows):
    """Majority NYU40 label per instance over the converted frames' true pixels (ties: smaller id)."""
    counts = {}
    for row in rows:
        truth = truth_for(inputs, row)
        for i, s in zip(truth.instance.ravel(), truth.semantic.ravel(), strict=True):
            if i >= 1 and 1 <= s <= 40:
                counts.setdefault(int(i), np.zeros(41, int))[s] += 1
    return {i: int(np.argmax(c)) for i, c in counts.items()}


def test_masks_categories_boxes_and_nearest_depths_match_the_truth(native, inputs):
    for scene_id, rows in rows_by_scene(native).items():
        categories = expected_categories(inputs, rows)
        assert categories.get(7) in (None, 7)  # the table outweighs the box of otherprop on top of it
        for row in rows:
            truth = truth_for(inputs, row)
            expected = {}
            for instance_id in np.unique(truth.instance[truth.instance >= 1]).tolist():
                mask = truth.instance == instance_id
                if instance_id in categories and mask.sum() >= MIN_PIXELS:
                    expected[instance_id] = mask
            got = {inst["instance_id"]: inst for inst in row["instances"]}
            assert set(got) == set(expected), (scene_id, row["view_id"])
            depth = decode_depth(row["depth"])
            for instance_id, inst in got.items():
                mask = expected[instance_id]
                assert (decode_mask(inst["mask"]) == mask).all()
                assert inst["category_id"] == categories[instance_id]
                rows_, cols_ = np.nonzero(mask)
                assert inst["box_xyxy"] == [cols_.min(), rows_.min(), cols_.max() + 1, rows_.max() + 1]
                true_min = np.nanmin(np.where(np.isfinite(depth) & mask, truth.planar, np.nan))
                assert abs(inst["depth_min"] - true_min) <= tolerance(true_min)
            assert 12 not in got  # the unlabelled box is never an instance


def test_poses_are_opencv_camera_to_world_in_metres(native, inputs):
    for rows in rows_by_scene(native).values():
        for row in rows:
            scene, camera = row["scene_id"].split("/")
            synthetic = inputs.scenes[scene]
            key = synthetic.trajectories[camera][row["view_id"]]
            pose = frame_pose(row)
            np.testing.assert_allclose(pose[:3, 3], key.position * synthetic.meters_per_asset_unit, rtol=1e-12)
            np.testing.assert_allclose(pose[:3, :3], key.orientation @ np.diag([1.0, -1.0, -1.0]), atol=1e-12)


def test_images_are_hypersims_tone_mapping(native, inputs):
    """Independent transcription of scene_generate_images_tonemap.py in float64 with np.percentile."""
    for rows in rows_by_scene(native).values():
        for row in rows:
            truth = truth_for(inputs, row)
            rgb = truth.rgb.astype(np.float16).astype(np.float64)
            valid = truth.entity != -1
            brightness = 0.3 * rgb[..., 0] + 0.59 * rgb[..., 1] + 0.11 * rgb[..., 2]
            scale = 0.8**2.2 / np.percentile(brightness[valid], 90)
            expected = np.clip(np.power(np.maximum(scale * rgb, 0), 1 / 2.2), 0, 1) * 255
            got = decode_image(row["image"]).astype(np.float64)
            assert np.abs(got - expected).max() <= 0.6


def test_half_resolution_masks_follow_the_truth(half, inputs):
    for rows in rows_by_scene(half).values():
        for row in rows:
            truth = truth_for(inputs, row)
            for inst in row["instances"]:
                mask, true = decode_mask(inst["mask"]), truth.instance == inst["instance_id"]
                if true.sum() >= 20:
                    assert (mask & true).sum() / (mask | true).sum() > 0.6


def test_exr_input_gives_the_same_records(native, exr_native):
    hdf5, exr = rows_by_scene(native), rows_by_scene(exr_native)
    assert set(hdf5) == set(exr)
    compared = 0
    for scene_id in hdf5:
        exr_rows = {r["view_id"]: r for r in exr[scene_id]}
        for a in hdf5[scene_id]:
            b = exr_rows.get(a["view_id"])
            if b is None:
                continue
            compared += 1
            np.testing.assert_array_equal(frame_K(a), frame_K(b))
            np.testing.assert_array_equal(frame_pose(a), frame_pose(b))
            assert [(i["instance_id"], i["category_id"], i["mask"]) for i in a["instances"]] == [
                (i["instance_id"], i["category_id"], i["mask"]) for i in b["instances"]
            ]
            da, db = decode_depth(a["depth"]), decode_depth(b["depth"])
            both = np.isfinite(da) & np.isfinite(db)
            assert both.sum() > 0.5 * da.size
            assert (np.abs(da - db)[both] <= tolerance(da[both])).all()
            image_a, image_b = decode_image(a["image"]).astype(int), decode_image(b["image"]).astype(int)
            assert np.abs(image_a - image_b).max() <= 2
    assert compared >= 5
