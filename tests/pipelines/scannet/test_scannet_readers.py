"""The .sens and exported-folder readers recover exactly what the fixture writers stored, and refuse
broken input with an error naming the file."""

from __future__ import annotations

import struct

import cv2
import numpy as np
import pytest

from pipelines.scannet.exported import ExportedScan
from pipelines.scannet.scan import encoded_image_size, rigid_pose
from pipelines.scannet.sens import SensScan
from tests.pipelines.scannet.synthetic_scan import SyntheticScan, write_exported, write_sens
from usl.errors import UslError


def _check_scan_matches(reader, synthetic) -> None:
    scan = synthetic.scan
    cal = reader.calibration
    assert cal.color_size == scan.color_size and cal.depth_size == scan.depth_size
    assert cal.depth_shift == 1000.0
    # stored with integer pixel centres (and float32 in .sens); read back with +0.5 centres
    np.testing.assert_allclose(cal.K_color, scan.K_color, rtol=1e-6, atol=1e-4)
    np.testing.assert_allclose(cal.K_depth, scan.K_depth, rtol=1e-6, atol=1e-4)
    assert reader.frame_indices == list(range(scan.num_frames))
    for frame in synthetic.frames:
        i = frame.index
        assert reader.color_encoded(i) == frame.color
        decoded = cv2.cvtColor(cv2.imdecode(np.frombuffer(frame.color, np.uint8), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)
        np.testing.assert_array_equal(reader.color(i), decoded)
        np.testing.assert_array_equal(reader.depth_raw(i), frame.depth_mm)
        depth = reader.depth(i)
        np.testing.assert_array_equal(np.isnan(depth), frame.depth_mm == 0)
        np.testing.assert_allclose(depth[frame.depth_mm > 0], frame.depth_mm[frame.depth_mm > 0] / 1000.0, rtol=1e-6)
        pose = reader.pose(i)
        assert pose.dtype == np.float64 and pose.shape == (4, 4)
        np.testing.assert_array_equal(pose.astype(np.float32), frame.pose)
        assert (rigid_pose(pose) is None) == (i in synthetic.lost)


def test_sens_reader_recovers_everything(synthetic):
    with SensScan(synthetic.sens) as reader:
        assert reader.scene_id == "scene0001_00" and reader.color_codec == "jpeg"
        _check_scan_matches(reader, synthetic)


def test_exported_reader_recovers_everything(synthetic):
    _check_scan_matches(ExportedScan(synthetic.exported), synthetic)


def test_exported_frames_sort_numerically(tmp_path):
    scan = SyntheticScan(num_frames=12, color_size=(32, 24), depth_size=(16, 12))
    frames = [f for f in scan.frames() if f.index in (0, 2, 10, 11)]  # "10" sorts before "2" as text
    write_exported(tmp_path, scan, frames)
    assert ExportedScan(tmp_path).frame_indices == [0, 2, 10, 11]


def test_rigid_pose_rejects_and_cleans():
    assert rigid_pose(np.full((4, 4), -np.inf)) is None
    bad = np.eye(4)
    bad[0, 0] = np.nan
    assert rigid_pose(bad) is None
    assert rigid_pose(np.diag([2.0, 1.0, 1.0, 1.0])) is None  # scaled: not rigid
    assert rigid_pose(np.diag([-1.0, 1.0, 1.0, 1.0])) is None  # reflection
    rng = np.random.default_rng(0)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = q, [1.0, -2.0, 0.5]
    cleaned = rigid_pose(pose.astype(np.float32))
    assert np.abs(cleaned[:3, :3].T @ cleaned[:3, :3] - np.eye(3)).max() < 1e-12
    np.testing.assert_allclose(cleaned, pose, atol=1e-6)


@pytest.mark.parametrize("size", [(97, 61), (1296, 968), (640, 480)])
def test_encoded_image_size_reads_headers(size):
    image = np.zeros((size[1], size[0], 3), np.uint8)
    for ext in (".jpg", ".png"):
        ok, data = cv2.imencode(ext, image)
        assert ok and encoded_image_size(data.tobytes()) == size
    assert encoded_image_size(b"not an image") is None


# -- broken input ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny():
    scan = SyntheticScan(num_frames=3, color_size=(32, 24), depth_size=(16, 12))
    return scan, list(scan.frames())


def test_truncated_sens_is_refused_up_front(tmp_path, tiny):
    scan, frames = tiny
    path = tmp_path / "scene0009_00.sens"
    write_sens(path, scan, frames, imu_records=0)
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 10])
    with pytest.raises(UslError, match=r"scene0009_00\.sens: truncated .*frame 2 of 3"):
        SensScan(path)


def test_proprietary_depth_codec_is_refused(tmp_path, tiny):
    scan, frames = tiny
    path = tmp_path / "occi.sens"
    write_sens(path, scan, frames, depth_codec=2)
    with pytest.raises(UslError, match=r"occi\.sens: .*proprietary occi_ushort"):
        SensScan(path)


def test_not_a_sens_file_is_refused(tmp_path):
    path = tmp_path / "x.sens"
    path.write_bytes(struct.pack("<I", 3) + bytes(100))
    with pytest.raises(UslError, match=r"x\.sens: \.sens version 3"):
        SensScan(path)


def test_depth_size_mismatch_names_file_and_frame(tmp_path, tiny):
    scan, _ = tiny
    other = SyntheticScan(num_frames=2, color_size=(32, 24), depth_size=(20, 15))
    path = tmp_path / "mismatch.sens"
    write_sens(path, scan, other.frames())  # header: 16x12 depth; payload: 20x15
    with SensScan(path) as reader:
        with pytest.raises(UslError, match=r"mismatch\.sens: frame 0 depth .*16x12"):
            reader.depth(0)


def test_colour_size_mismatch_names_file_and_frame(tmp_path, tiny):
    scan, _ = tiny
    other = SyntheticScan(num_frames=2, color_size=(40, 30), depth_size=(16, 12))
    path = tmp_path / "colour.sens"
    write_sens(path, scan, other.frames())  # header: 32x24 colour; payload: 40x30
    with SensScan(path) as reader:
        with pytest.raises(UslError, match=r"colour\.sens: frame 1 colour is 40x30, header says 32x24"):
            reader.color_encoded(1)


def test_colour_and_depth_of_different_aspect_are_refused(tmp_path):
    scan = SyntheticScan(num_frames=1, color_size=(32, 24), depth_size=(24, 24))
    path = tmp_path / "aspect.sens"
    write_sens(path, scan, scan.frames())
    with pytest.raises(UslError, match=r"aspect\.sens: colour 32x24 and depth 24x24"):
        SensScan(path)


def test_exported_missing_and_inconsistent_files_are_named(tmp_path, tiny):
    scan, frames = tiny
    write_exported(tmp_path, scan, frames)
    (tmp_path / "pose" / "1.txt").unlink()
    reader = ExportedScan(tmp_path)
    with pytest.raises(UslError, match=r"pose/1\.txt: missing"):
        reader.pose(1)
    cv2.imwrite(str(tmp_path / "depth" / "2.png"), np.zeros((10, 10), np.uint16))
    with pytest.raises(UslError, match=r"depth/2\.png: depth is 10x10"):
        reader.depth(2)
    (tmp_path / "pose" / "2.txt").write_text("1 2 3\n")
    with pytest.raises(UslError, match=r"pose/2\.txt"):
        reader.pose(2)
