"""What ARKit capture apps export in nerfstudio's format: intrinsics per frame (autofocus changes the
focal length) and depth at a lower resolution than colour. Both come out on the one pinhole camera."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
from pycocotools import mask as mask_utils

from pipelines.captures.cli import main
from tests.pipelines.captures.synthetic_capture import rle
from usl.records import decode_depth, decode_image, load_manifest

from .test_captures_convert import check_objects, read_frames

ZOOMED, ZOOM = 9, 1.04  # this frame's focal length is 4 % longer


def zoom_map(K: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel of the zoomed frame lies in the original (OpenCV pixel indices)."""
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    x = K[0, 2] + (u + 0.5 - K[0, 2]) / ZOOM - 0.5
    y = K[1, 2] + (v + 0.5 - K[1, 2]) / ZOOM - 0.5
    return x.astype(np.float32), y.astype(np.float32)


def test_per_frame_intrinsics_and_low_resolution_depth(capture, tmp_path):
    truth = capture.truth
    folder = tmp_path / "app"
    shutil.copytree(capture.root / "nerfstudio", folder)
    name = truth.names[ZOOMED]
    map_x, map_y = zoom_map(truth.K, truth.width, truth.height)
    image = cv2.remap(cv2.cvtColor(truth.images[ZOOMED], cv2.COLOR_RGB2BGR), map_x, map_y, cv2.INTER_LINEAR)
    cv2.imwrite(str(folder / "images" / name), image)
    data = json.loads((folder / "transforms.json").read_text())
    for entry in data["frames"]:
        if entry["file_path"].endswith(name):
            entry.update(fl_x=ZOOM * truth.K[0, 0], fl_y=ZOOM * truth.K[1, 1])
    (folder / "transforms.json").write_text(json.dumps(data))
    detections = json.loads((folder / "detections.json").read_text())
    for det in detections:
        if det["file_name"].endswith(name):
            mask = mask_utils.decode({"size": det["segmentation"]["size"], "counts": det["segmentation"]["counts"]})
            det["segmentation"] = rle(cv2.remap(mask, map_x, map_y, cv2.INTER_NEAREST))
    (folder / "detections.json").write_text(json.dumps(detections))
    for k, frame_name in enumerate(truth.names):  # depth at half the colour resolution
        depth = np.round(truth.depth[k] * 1000).astype(np.uint16)
        half = cv2.resize(depth, (truth.width // 2, truth.height // 2), interpolation=cv2.INTER_NEAREST)
        cv2.imwrite(str(folder / "depth" / frame_name), half)

    out = tmp_path / "records"
    assert main([str(folder), "--out", str(out), "--quiet", "--resolution", "native"]) == 0
    frames = read_frames(out)
    check_objects(frames, truth, {c["id"]: c["name"] for c in load_manifest(out)["categories"]})
    for frame in frames:
        np.testing.assert_allclose(np.asarray(frame["K"]).reshape(3, 3), truth.K)
        if frame["view_id"] == ZOOMED:
            continue
        # each output pixel takes the half-resolution depth pixel under its centre
        half = cv2.imread(str(folder / "depth" / truth.names[frame["view_id"]]), cv2.IMREAD_UNCHANGED) / 1000
        want = np.repeat(np.repeat(half, 2, axis=0), 2, axis=1)
        depth = np.nan_to_num(decode_depth(frame["depth"]))
        assert (np.abs(depth - want) <= 1e-3).mean() > 0.999
    zoomed = next(f for f in frames if f["view_id"] == ZOOMED)
    inner = (slice(12, -12), slice(16, -16))
    got = cv2.cvtColor(decode_image(zoomed["image"]), cv2.COLOR_RGB2GRAY).astype(np.float64)[inner]
    want = cv2.cvtColor(truth.images[ZOOMED], cv2.COLOR_RGB2GRAY).astype(np.float64)[inner]
    (dx, dy), _ = cv2.phaseCorrelate(want, got)
    assert np.hypot(dx, dy) < 0.1
