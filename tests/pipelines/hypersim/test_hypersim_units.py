"""The converter's pieces against independent oracles: camera maths, tone mapping, resampling,
instance extraction, metadata parsing and frame readers."""

import math

import h5py
import numpy as np
import pytest
import torch

from pipelines.hypersim.camera import (
    check_camera_model,
    intrinsics_from_m_cam_from_uv,
    load_trajectory,
    planar_depth_factor,
)
from pipelines.hypersim.frames import read_exr_frame, read_hdf5
from pipelines.hypersim.instances import category_votes, instance_entries
from pipelines.hypersim.metadata import read_camera_csv, read_meters_per_asset_unit, read_split_csv
from pipelines.hypersim.paths import FrameSkip, TrajectoryPaths
from pipelines.hypersim.resample import Resampler
from pipelines.hypersim.tonemap import apply_tonemap, percentile, tonemap_scale
from tests.pipelines.hypersim.hypersim_fixture import (
    CANONICAL_M,
    TILT_SHIFT_M,
    make_scene,
    render,
    write_exr,
    write_hdf5,
)
from usl.errors import UslError
from usl.geometry.cameras import project, scale_intrinsics
from usl.records import make_instance

# --- cameras -------------------------------------------------------------------------------------


def test_canonical_camera_is_the_documented_60_degree_pinhole():
    """Hypersim's canonical scenes: 60 deg horizontal FoV, focal 886.81 px at 1024x768, centred."""
    K = intrinsics_from_m_cam_from_uv(CANONICAL_M, 1024, 768)
    np.testing.assert_allclose(K, [[886.8100134752651, 0, 512], [0, 886.8100134752651, 384], [0, 0, 1]], atol=1e-9)


@pytest.mark.parametrize("m", [TILT_SHIFT_M, CANONICAL_M])
def test_K_sends_hypersims_pixel_rays_to_pixel_centres(m):
    """Rays built as in contrib/mikeroberts3000 notebook 01 (linspace uv grid) project to (j+.5, i+.5)."""
    width, height = 16, 12
    half_u, half_v = 1.0 / width, 1.0 / height
    u, v = np.meshgrid(np.linspace(-1 + half_u, 1 - half_u, width), np.linspace(-1 + half_v, 1 - half_v, height)[::-1])
    rays_gl = np.stack([u, v, np.ones_like(u)], -1) @ m.T
    rays_cv = rays_gl * [1.0, -1.0, -1.0]
    K = intrinsics_from_m_cam_from_uv(m, width, height)
    uv, w = project(torch.from_numpy(rays_cv.reshape(-1, 3)), torch.from_numpy(K))
    jj, ii = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    np.testing.assert_allclose(uv.numpy(), np.stack([jj, ii], -1).reshape(-1, 2), atol=1e-9)
    assert (w > 0).all()


# Scene ai_037_002 (tilt-shift) in contrib/mikeroberts3000/metadata_camera_parameters.csv: its ray
# matrix and, independently, the OpenGL projection matrix Hypersim publishes for projecting points.
AI_037_002_M_CAM_FROM_UV = np.array(
    [
        0.579607251426182,
        0.0,
        -0.06955286861651404,
        0.0,
        0.4346865334657201,
        0.09273312506660672,
        -0.0,
        0.004054126980668954,
        -1.003909173803896,
    ]
).reshape(3, 3)
AI_037_002_M_PROJ = np.array(
    [
        1.7253062268275619,
        0.001113868662274642,
        -0.11942983282195321,
        0.0,
        0.0,
        2.2985281393428907,
        0.21231970279458348,
        0.0,
        0.0,
        0.009300822120943601,
        -0.9972411188430887,
        -2.002002002002002,
        0.0,
        0.009282239059762895,
        -0.9952486290951505,
        0.0,
    ]
).reshape(4, 4)


def test_K_agrees_with_hypersims_projection_matrix():
    """Points projected by M_proj (NDC [-1, 1] spanning the image) land where our K puts them."""
    rng = np.random.default_rng(0)
    points_gl = np.c_[rng.uniform(-1, 1, 50), rng.uniform(-1, 1, 50), -rng.uniform(0.5, 8, 50)]
    clip = np.c_[points_gl, np.ones(50)] @ AI_037_002_M_PROJ.T
    ndc = clip[:, :2] / clip[:, 3:]
    expected = np.c_[(ndc[:, 0] + 1) * 1024 / 2, (1 - ndc[:, 1]) * 768 / 2]
    K = intrinsics_from_m_cam_from_uv(AI_037_002_M_CAM_FROM_UV, 1024, 768)
    uv, _ = project(torch.from_numpy(points_gl * [1.0, -1.0, -1.0]), torch.from_numpy(K))
    np.testing.assert_allclose(uv.numpy(), expected, atol=1e-6)


def test_tilt_shift_K_is_not_upper_triangular():
    K = intrinsics_from_m_cam_from_uv(TILT_SHIFT_M, 1024, 768)
    assert abs(K[2, 1]) > 1e-6 and K[2, 2] == 1.0


@pytest.mark.parametrize("m", [TILT_SHIFT_M, CANONICAL_M])
def test_resizing_is_a_pure_scale_of_K(m):
    direct = intrinsics_from_m_cam_from_uv(m, 256, 96)
    scaled = scale_intrinsics(torch.from_numpy(intrinsics_from_m_cam_from_uv(m, 1024, 768)), 0.25, 0.125).numpy()
    np.testing.assert_allclose(scaled / scaled[2, 2], direct, rtol=1e-12, atol=1e-12)


def test_planar_depth_factor_turns_distance_into_camera_z():
    scene = make_scene(width=40, height=30)
    truth = render(scene, "cam_00", 2)
    factor = planar_depth_factor(scene.m_cam_from_uv, 40, 30)
    ok = np.isfinite(truth.distance)
    np.testing.assert_allclose((truth.distance * factor)[ok], truth.planar[ok], rtol=1e-6)


def test_bad_camera_models_are_refused():
    with pytest.raises(UslError, match="singular"):
        check_camera_model(np.zeros((3, 3)), "cams.csv: scene x")
    with pytest.raises(UslError, match="look down -z"):
        check_camera_model(np.diag([0.5, 0.4, 1.0]), "cams.csv: scene x")


def _trajectory(tmp_path, orientations, frame_indices):
    paths = TrajectoryPaths(tmp_path / "ai_001_001", "cam_00")
    n = len(orientations)
    write_hdf5(paths.keyframes("positions"), np.arange(3 * n, dtype=np.float64).reshape(n, 3))
    write_hdf5(paths.keyframes("orientations"), np.asarray(orientations))
    if frame_indices is not None:
        write_hdf5(paths.keyframes("frame_indices"), np.asarray(frame_indices))
    return paths


def test_poses_are_found_by_frame_number_not_by_row(tmp_path):
    angles = [0.1, 0.5, 0.9, 1.3]
    rot = [np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1.0]]) for a in angles]
    trajectory = load_trajectory(_trajectory(tmp_path, rot, [7, 3, 5, 0]))
    pose = trajectory.camera_to_world(5, meters_per_asset_unit=0.5)
    np.testing.assert_allclose(pose[:3, 3], [3.0, 3.5, 4.0])  # row 2, scaled to metres
    np.testing.assert_allclose(pose[:3, :3], rot[2] @ np.diag([1.0, -1.0, -1.0]), atol=1e-12)
    with pytest.raises(FrameSkip, match="no camera keyframe for frame 4"):
        trajectory.camera_to_world(4, 1.0)


def test_orientations_must_be_rotations(tmp_path):
    noisy = np.eye(3) + 1e-6 * np.arange(9).reshape(3, 3)
    trajectory = load_trajectory(_trajectory(tmp_path, [noisy, 1.2 * np.eye(3), np.diag([1.0, 1.0, -1.0])], None))
    snapped = trajectory.camera_to_world(0, 1.0)[:3, :3]
    np.testing.assert_allclose(snapped.T @ snapped, np.eye(3), atol=1e-12)
    for frame in (1, 2):  # scaled; a reflection
        with pytest.raises(FrameSkip, match="not a rotation"):
            trajectory.camera_to_world(frame, 1.0)


def test_broken_pose_files_name_the_file(tmp_path):
    paths = _trajectory(tmp_path, [np.eye(3)] * 2, None)
    write_hdf5(paths.keyframes("orientations"), np.stack([np.eye(3)] * 3))
    with pytest.raises(UslError, match="camera_keyframe_orientations.hdf5: shape"):
        load_trajectory(paths)
    paths.keyframes("positions").unlink()
    with pytest.raises(UslError, match="camera_keyframe_positions.hdf5: file not found"):
        load_trajectory(paths)


# --- tone mapping --------------------------------------------------------------------------------


@pytest.mark.parametrize("n", [1, 2, 7, 1000, 12345])
def test_percentile_equals_numpy(n):
    values = np.random.default_rng(n).lognormal(size=n).astype(np.float32)
    assert percentile(values.copy(), 90) == pytest.approx(float(np.percentile(values, 90)), rel=1e-6)


def test_tonemap_scale_rules():
    rgb = np.full((4, 4, 3), 2.0, np.float32)
    none = np.zeros((4, 4), bool)
    assert tonemap_scale(rgb, none) == 1.0  # no pixel with geometry
    assert tonemap_scale(rgb * 1e-6, ~none) == 0.0  # too dark to scale
    assert tonemap_scale(rgb, ~none) == pytest.approx(0.8**2.2 / 2.0)
    image = apply_tonemap(rgb, 0.8**2.2 / 2.0)
    assert (image == round(0.8 * 255)).all()
    rgb[0, 0] = np.nan
    assert apply_tonemap(rgb, 1.0)[0, 0].tolist() == [0, 0, 0]


# --- resampling ----------------------------------------------------------------------------------


def plane_depth(K, width, height, normal=(0.1, -0.3, 0.4), offset=2.0):
    """Planar depth of the plane n . X = offset seen through K at every pixel centre."""
    jj, ii = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    rays = np.stack([jj, ii, np.ones_like(jj)], -1) @ np.linalg.inv(K).T
    rays /= rays[..., 2:]
    return offset / (rays @ np.asarray(normal))


@pytest.mark.parametrize("m", [TILT_SHIFT_M, CANONICAL_M])
@pytest.mark.parametrize("size", [(32, 24), (40, 30), (50, 20)])
def test_depth_resampling_is_exact_on_a_slanted_plane(size, m):
    K = intrinsics_from_m_cam_from_uv(m, 64, 48)
    source = plane_depth(K, 64, 48).astype(np.float32)
    out = Resampler(64, 48, *size, K).depth(source)
    scaled = scale_intrinsics(torch.from_numpy(K), size[0] / 64, size[1] / 48).numpy()
    np.testing.assert_allclose(out, plane_depth(scaled, *size), rtol=2e-6)


def test_depth_resampling_invents_no_depth_between_objects():
    source = np.full((48, 64), 2.0, np.float32)
    source[:, 31:] = 5.0
    source[10:20, 5:9] = np.nan
    out = Resampler(64, 48, 24, 18, np.eye(3)).depth(source)
    values = set(np.unique(out[np.isfinite(out)]).tolist())
    assert values == {2.0, 5.0}


def test_labels_take_the_source_pixel_under_the_output_centre():
    source = np.arange(48 * 64).reshape(48, 64)
    out = Resampler(64, 48, 20, 15, np.eye(3)).labels(source)
    rows = np.floor((np.arange(15) + 0.5) * 48 / 15).astype(int)
    cols = np.floor((np.arange(20) + 0.5) * 64 / 20).astype(int)
    np.testing.assert_array_equal(out, source[np.ix_(rows, cols)])


def test_colour_is_area_averaged():
    rgb = np.random.default_rng(0).random((48, 64, 3)).astype(np.float32)
    out = Resampler(64, 48, 32, 24, np.eye(3)).colour(rgb)
    np.testing.assert_allclose(out, rgb.reshape(24, 2, 32, 2, 3).mean(axis=(1, 3)), rtol=1e-5)


# --- instances -----------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", range(12))
def test_instance_entries_equal_make_instance(seed):
    rng = np.random.default_rng(seed)
    h, w = rng.integers(1, 30, size=2)
    labels = rng.integers(-1, 6, (h, w)).astype(np.int16)
    if seed % 2:
        labels = np.where(rng.random((h, w)) < 0.7, np.int16(-1), np.int16(4))
        labels[:, -1] = 9  # a whole column: a run crossing column boundaries
    depth = rng.uniform(0.5, 5, (h, w)).astype(np.float32)
    depth[rng.random((h, w)) < 0.3] = np.nan
    entries = instance_entries(labels, depth)
    assert [e["instance_id"] for e in entries] == sorted(set(labels[labels >= 1].tolist()))
    for entry in entries:
        expected = make_instance(entry["instance_id"], 3, labels == entry["instance_id"], depth)
        got = dict(entry, category_id=3)
        assert got.keys() == expected.keys()
        for key in ("instance_id", "mask", "box_xyxy", "area"):
            assert got[key] == expected[key], key
        assert (math.isnan(got["depth_min"]) and math.isnan(expected["depth_min"])) or (
            got["depth_min"] == expected["depth_min"]
        )


def test_instance_entries_of_an_empty_frame():
    assert instance_entries(np.full((5, 4), -1, np.int16), None) == []


def test_category_votes_count_pixels_per_label():
    rng = np.random.default_rng(3)
    instance = rng.integers(-1, 5, (20, 30)).astype(np.int16)
    semantic = rng.integers(-1, 42, (20, 30)).astype(np.int16)
    ids, votes = category_votes(instance, semantic)
    assert ids.tolist() == sorted(set(instance[instance >= 1].tolist()))
    for instance_id, row in zip(ids, votes, strict=True):
        mask = instance == instance_id
        for label in range(1, 41):
            assert row[label] == ((semantic == label) & mask).sum()
        assert row[0] == (mask & ((semantic < 1) | (semantic > 40))).sum()


# --- metadata and readers ------------------------------------------------------------------------


def test_split_csv_problems_name_the_file(tmp_path):
    path = tmp_path / "split.csv"
    path.write_text("scene_name,camera_name,frame_id\nai_001_001,cam_00,0\n")
    with pytest.raises(UslError, match=r"split\.csv: missing column\(s\) included_in_public_release"):
        read_split_csv(path)
    header = "scene_name,camera_name,frame_id,included_in_public_release,exclude_reason,split_partition_name\n"
    path.write_text(header + "ai_001_001,cam_00,0,True,,train\nai_001_001,cam_00,1,True,,val\n")
    with pytest.raises(UslError, match=r"split\.csv:3: ai_001_001/cam_00 is in both"):
        read_split_csv(path)
    with pytest.raises(UslError, match="nope.csv: file not found"):
        read_camera_csv(tmp_path / "nope.csv")


def test_scene_units_come_from_metadata_scene_csv(tmp_path):
    detail = tmp_path / "ai_001_001" / "_detail"
    detail.mkdir(parents=True)
    (detail / "metadata_scene.csv").write_text("parameter_name,parameter_value\nmeters_per_asset_unit,0.0254\n")
    assert read_meters_per_asset_unit(tmp_path / "ai_001_001") == 0.0254
    (detail / "metadata_scene.csv").write_text("parameter_name,parameter_value\nmeters_per_asset_unit,-1\n")
    with pytest.raises(UslError, match="metadata_scene.csv: meters_per_asset_unit '-1'"):
        read_meters_per_asset_unit(tmp_path / "ai_001_001")


def test_hdf5_without_dataset_is_a_frame_skip(tmp_path):
    with h5py.File(tmp_path / "x.hdf5", "w") as f:
        f.create_dataset("other", data=np.zeros(3))
    with pytest.raises(FrameSkip, match="unreadable depth_meters HDF5"):
        read_hdf5(tmp_path / "x.hdf5", "depth_meters")


def test_exr_frames_accept_integer_entity_ids_and_refuse_broken_files(tmp_path):
    scene = make_scene(width=16, height=12)
    truth = render(scene, "cam_00", 0)
    paths = TrajectoryPaths(tmp_path / scene.name, "cam_00")
    geometry = {f"VRayPosition.{c}": truth.position[..., k] for k, c in enumerate("RGB")}
    geometry["VRayRenderEntityID"] = np.where(truth.entity > 0, truth.entity, 0).astype(np.uint32)
    write_exr(paths.geometry_exr(0), geometry)
    write_exr(paths.final_exr(0), {c: truth.rgb[..., k] for k, c in enumerate("RGB")})
    write_hdf5(paths.geometry_hdf5(0, "semantic"), truth.semantic)
    write_hdf5(paths.geometry_hdf5(0, "semantic_instance"), truth.instance)
    key = scene.trajectories["cam_00"][0]
    raw = read_exr_frame(paths, 0, key.position, scene.meters_per_asset_unit)
    np.testing.assert_array_equal(raw.entity, truth.entity)
    np.testing.assert_allclose(raw.distance, truth.distance, rtol=1e-5)
    del geometry["VRayPosition.G"]
    write_exr(paths.geometry_exr(0), geometry)
    with pytest.raises(FrameSkip, match="EXR lacks channel"):
        read_exr_frame(paths, 0, key.position, scene.meters_per_asset_unit)
    data = paths.final_exr(0).read_bytes()
    paths.final_exr(0).write_bytes(data[: len(data) // 3])
    geometry["VRayPosition.G"] = truth.position[..., 1]
    write_exr(paths.geometry_exr(0), geometry)
    with pytest.raises(FrameSkip, match="unreadable EXR"):
        read_exr_frame(paths, 0, key.position, scene.meters_per_asset_unit)
