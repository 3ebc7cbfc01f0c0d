"""Frames with lens distortion (nerfstudio's OPENCV k1 k2 p1 p2) come out on the pinhole camera: the
rendered capture is distorted with OpenCV's own model, converted, and compared with the pinhole truth."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np

from pipelines.captures.cli import main
from tests.pipelines.captures.synthetic_capture import rle
from usl.records import decode_image, load_manifest

from .test_captures_convert import check_objects, read_frames

DISTORTION = np.array([-0.08, 0.02, 0.002, -0.001, 0.0])  # k1 k2 p1 p2 k3


def distortion_map(K: np.ndarray, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """For every pixel of the distorted image, where it lies in the pinhole image (OpenCV pixel indices).

    OpenCV's (and nerfstudio's) model, inverted by fixed-point iteration in numpy.
    """
    k1, k2, p1, p2, k3 = DISTORTION
    v, u = np.mgrid[0:height, 0:width].astype(np.float64)
    xd, yd = (u + 0.5 - K[0, 2]) / K[0, 0], (v + 0.5 - K[1, 2]) / K[1, 1]
    x, y = xd.copy(), yd.copy()
    for _ in range(100):
        r2 = x * x + y * y
        radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
        x = (xd - (2 * p1 * x * y + p2 * (r2 + 2 * x * x))) / radial
        y = (yd - (p1 * (r2 + 2 * y * y) + 2 * p2 * x * y)) / radial
    map_x = x * K[0, 0] + K[0, 2] - 0.5
    map_y = y * K[1, 1] + K[1, 2] - 0.5
    return map_x.astype(np.float32), map_y.astype(np.float32)


def test_distorted_frames_are_undistorted(capture, tmp_path):
    truth = capture.truth
    folder = tmp_path / "distorted"
    shutil.copytree(capture.root / "nerfstudio", folder)
    map_x, map_y = distortion_map(truth.K, truth.width, truth.height)
    detections = json.loads((folder / "detections.json").read_text())
    for k, name in enumerate(truth.names):
        bgr = cv2.cvtColor(truth.images[k], cv2.COLOR_RGB2BGR)
        cv2.imwrite(str(folder / "images" / name), cv2.remap(bgr, map_x, map_y, cv2.INTER_LINEAR))
        depth = np.round(truth.depth[k] * 1000).astype(np.uint16)
        cv2.imwrite(str(folder / "depth" / name), cv2.remap(depth, map_x, map_y, cv2.INTER_NEAREST))
    for det in detections:  # the segmenter saw the distorted images
        k = truth.names.index(det["file_name"].rsplit("/", 1)[-1])
        mask = np.asfortranarray(
            cv2.remap(_decoded(det["segmentation"]), map_x, map_y, cv2.INTER_NEAREST), dtype=np.uint8
        )
        det["segmentation"] = rle(mask)
    (folder / "detections.json").write_text(json.dumps(detections))
    data = json.loads((folder / "transforms.json").read_text())
    data.update(k1=DISTORTION[0], k2=DISTORTION[1], p1=DISTORTION[2], p2=DISTORTION[3])
    (folder / "transforms.json").write_text(json.dumps(data))

    out = tmp_path / "records"
    assert main([str(folder), "--out", str(out), "--quiet", "--resolution", "native"]) == 0
    frames = read_frames(out)
    check_objects(frames, truth, {c["id"]: c["name"] for c in load_manifest(out)["categories"]})
    inner = (slice(12, -12), slice(16, -16))  # the corners the distorted image does not cover
    for frame in frames[::6]:
        np.testing.assert_allclose(np.asarray(frame["K"]).reshape(3, 3), truth.K)
        got = cv2.cvtColor(decode_image(frame["image"]), cv2.COLOR_RGB2GRAY).astype(np.float64)[inner]
        want = cv2.cvtColor(truth.images[frame["view_id"]], cv2.COLOR_RGB2GRAY).astype(np.float64)[inner]
        (dx, dy), _ = cv2.phaseCorrelate(want, got)
        assert np.hypot(dx, dy) < 0.1, (frame["view_id"], dx, dy)  # a pixel-centre slip would be 0.5


def _decoded(segmentation: dict) -> np.ndarray:
    from pycocotools import mask as mask_utils

    return mask_utils.decode({"size": segmentation["size"], "counts": segmentation["counts"].encode()})
