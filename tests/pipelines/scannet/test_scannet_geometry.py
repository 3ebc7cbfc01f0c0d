"""Output grid (K, depth registration, mask resampling) and depth+pose mask warping, against
ScanNet's published calibration and the synthetic scene's ray-cast truth."""

from __future__ import annotations

import numpy as np
import pytest
from pycocotools import mask as mask_utils

from pipelines.scannet.convert import ConvertOptions, open_scan, track_scan
from pipelines.scannet.grid import OutputGrid
from pipelines.scannet.quality import tracking_quality
from pipelines.scannet.scan import Calibration, half_pixel_intrinsics
from pipelines.scannet.scannet_labels import ScanNetLabelsSource
from pipelines.scannet.tracker import TrackerConfig
from pipelines.scannet.warp import DepthWarp
from tests.pipelines.scannet.synthetic_scan import SyntheticScan

# scene0000_00's intrinsic_color.txt / intrinsic_depth.txt (integer pixel centres, as ScanNet stores them)
SCANNET_COLOR = [[1169.621094, 0, 646.295044, 0], [0, 1167.105103, 489.927032, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
SCANNET_DEPTH = [[577.590698, 0, 318.905426, 0], [0, 578.729797, 242.683609, 0], [0, 0, 1, 0], [0, 0, 0, 1]]


def encode(mask: np.ndarray) -> dict:
    return mask_utils.encode(np.asfortranarray(mask.astype(np.uint8)))


def test_scannet_depth_intrinsics_are_the_colour_ones_resized_with_half_pixel_centres():
    """ScanNet's depth K equals its colour K scaled to 640x480 only under the +0.5 convention, so
    the 640x480 output grid is the depth camera itself and depth registration is the identity."""
    cal = Calibration(
        (1296, 968),
        (640, 480),
        half_pixel_intrinsics(np.array(SCANNET_COLOR), "c"),
        half_pixel_intrinsics(np.array(SCANNET_DEPTH), "d"),
        1000.0,
    )
    grid = OutputGrid.for_scan(cal, (640, 480))
    np.testing.assert_allclose(grid.K, cal.K_depth, atol=5e-3)
    np.testing.assert_array_equal(grid.depth_index, np.arange(640 * 480))
    naive = np.array(SCANNET_COLOR)[:3, :3] * [[640 / 1296], [480 / 968], [1]]  # scaling integer-centre K
    assert abs(naive[1, 2] - np.array(SCANNET_DEPTH)[1, 2]) > 0.2  # ... would be off by a quarter pixel


def test_registered_depth_matches_ray_cast_truth():
    scan = SyntheticScan(num_frames=1)  # colour 96x72, depth 48x36: depth pixel = 2x2 colour pixels
    cal = Calibration(scan.color_size, scan.depth_size, scan.K_color, scan.K_depth, 1000.0)
    grid = OutputGrid.for_scan(cal, None)  # colour resolution: depth is upsampled by the homography
    frame = scan.render(0)
    native = frame.depth_mm / 1000.0
    depth = grid.depth(native)
    rows, cols = np.arange(72) // 2, np.arange(96) // 2
    np.testing.assert_array_equal(depth, native[rows][:, cols])
    truth, _, _ = scan._cast(scan.true_pose(0), scan.K_color, scan.color_size)
    assert (np.abs(depth - truth) < 0.03 * truth).mean() > 0.9  # nearest lookup differs along edges only


@pytest.mark.parametrize("size", [(48, 36), (40, 30), (96, 72), (130, 97)])
def test_mask_resampling_samples_pixel_centres(size):
    scan = SyntheticScan(num_frames=1, color_size=(96, 72), depth_size=(48, 36))
    cal = Calibration(scan.color_size, scan.depth_size, scan.K_color, scan.K_depth, 1000.0)
    grid = OutputGrid.for_scan(cal, size)
    rng = np.random.default_rng(0)
    mask = rng.random((72, 96)) < 0.5
    rows = np.floor((np.arange(size[1]) + 0.5) * 72 / size[1]).astype(int)  # source pixel under each centre
    cols = np.floor((np.arange(size[0]) + 0.5) * 96 / size[0]).astype(int)
    np.testing.assert_array_equal(grid.mask(mask).astype(bool), mask[rows][:, cols])
    np.testing.assert_array_equal(grid.mask(np.asfortranarray(mask.astype(np.uint8))).astype(bool), mask[rows][:, cols])
    small = rng.random((size[1], size[0])) < 0.5
    back_rows = np.floor((np.arange(72) + 0.5) * size[1] / 72).astype(int)
    back_cols = np.floor((np.arange(96) + 0.5) * size[0] / 96).astype(int)
    np.testing.assert_array_equal(grid.to_frame(small, 72, 96).astype(bool), small[back_rows][:, back_cols])


@pytest.mark.parametrize("source", [0, 40, 80])
def test_warp_moves_masks_to_where_the_object_is(source):
    scan = SyntheticScan(num_frames=120)
    cal = Calibration(scan.color_size, scan.depth_size, scan.K_color, scan.K_depth, 1000.0)
    grid = OutputGrid.for_scan(cal, None)
    target = source + 20
    warp = DepthWarp(grid.K, grid.width, grid.height, tolerance=0.2)
    frames = [scan.render(source), scan.render(target)]
    for frame in frames:
        warp.add_frame(frame.index, grid.depth(frame.depth_mm / 1000.0), scan.true_pose(frame.index))
    for instance in (1, 2, 3):
        before, after = encode(frames[0].instances == instance), encode(frames[1].instances == instance)
        moved, covered = warp.warp(source, before), warp.covered(source, 72, 96)
        warped_iou = mask_utils.iou([mask_utils.merge([after, covered], intersect=True)], [moved], [0])[0, 0]
        raw_iou = mask_utils.iou([after], [before], [0])[0, 0]
        assert warped_iou > 0.75 and warped_iou > raw_iou + 0.1, (instance, warped_iou, raw_iou)
    assert warp.warp(source - 1, before) is None and warp.covered(source - 1, 72, 96) is None  # unknown frame


def test_warping_keeps_tracks_whole_at_large_stride(synthetic):
    labels = ScanNetLabelsSource(str(synthetic.labels), ((1, "chair"), (2, "couch"), (7, "tv")))
    with open_scan(synthetic.sens.parent, "scene0001_00") as scan:
        grid = OutputGrid.for_scan(scan.calibration, None)
        switches = {}
        for warp in ("on", "off"):
            options = ConvertOptions(stride=20, size=None, warp=warp, tracker=TrackerConfig(min_track_frames=2))
            tracked = track_scan(scan, labels.open_scan(scan), grid, options)
            observations = [
                (f, t.track_id, d.source_id)
                for t in tracked.tracks
                for f, d in zip(t.frames, t.detections, strict=True)
            ]
            quality = tracking_quality(observations)
            assert quality.purity == 1.0
            switches[warp] = quality.id_switches
    assert switches["on"] == 0 and switches["off"] >= 3
