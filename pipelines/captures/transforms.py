"""Reading nerfstudio / instant-ngp ``transforms.json``: intrinsics, camera-to-world poses, depth.

The file's keys (nerfstudio's data conventions): intrinsics ``fl_x fl_y cx cy w h`` (or instant-ngp's
``camera_angle_x``), ``camera_model`` ``OPENCV`` / ``PINHOLE`` / ``SIMPLE_PINHOLE`` with distortion
``k1 k2 k3 p1 p2``, each at the top level or overridden per frame; ``frames[]`` with ``file_path``,
``transform_matrix`` (camera-to-world, OpenGL axes: x right, y up, looking down -z) and optionally
``depth_file_path`` (16-bit depth, ``depth_unit_scale_factor`` metres per unit, default 0.001).
nerfstudio puts pixel centres at +0.5 like usl, so ``cx cy`` are taken as they are. Capture apps
(Polycam, Record3D and other ARKit exporters) write metric poses, so the poses count as metres
unless ``--scale`` says otherwise.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from pipelines.scannet.detections_file import load_json
from usl.errors import UslError

from .camera import FrameCamera
from .posed import MILLIMETRES, OPENGL_TO_OPENCV, CaptureFrame, PosedCapture, natural_key

TRANSFORMS = "transforms.json"
CAMERA_MODELS = ("OPENCV", "PINHOLE", "SIMPLE_PINHOLE")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".PNG", ".JPG", ".JPEG")


def _number(entry: dict[str, Any], base: dict[str, Any], key: str, where: str, default: float | None = None) -> float:
    value = entry.get(key, base.get(key, default))
    if value is None:
        raise UslError(f"{where}: no '{key}' (per frame or for the whole capture)")
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise UslError(f"{where}: '{key}' is {value!r}, not a finite number")
    return float(value)


def frame_camera(entry: dict[str, Any], base: dict[str, Any], where: str) -> FrameCamera:
    """The camera of one frame: its own keys over the file's."""
    width, height = int(_number(entry, base, "w", where)), int(_number(entry, base, "h", where))
    if "fl_x" in entry or "fl_x" in base:
        fx = _number(entry, base, "fl_x", where)
    else:  # instant-ngp's horizontal field of view
        fx = 0.5 * width / math.tan(0.5 * _number(entry, base, "camera_angle_x", where))
    fy = _number(entry, base, "fl_y", where, fx)
    cx = _number(entry, base, "cx", where, width / 2)
    cy = _number(entry, base, "cy", where, height / 2)
    model = entry.get("camera_model", base.get("camera_model", "OPENCV"))
    if model not in CAMERA_MODELS:
        raise UslError(f"{where}: camera_model {model!r} is not supported ({', '.join(CAMERA_MODELS)})")
    k1, k2, k3, p1, p2 = (_number(entry, base, k, where, 0.0) for k in ("k1", "k2", "k3", "p1", "p2"))
    if min(width, height) < 1 or fx <= 0 or fy <= 0:
        raise UslError(f"{where}: image size {width}x{height} or focal length {fx}, {fy} is not positive")
    distortion = (k1, k2, p1, p2, k3) if model == "OPENCV" else (0.0, 0.0, 0.0, 0.0, 0.0)
    return FrameCamera(width, height, (fx, fy, cx, cy), distortion)


def existing_file(folder: Path, name: Any, where: str) -> Path:
    """``name`` relative to ``folder``; instant-ngp's scenes leave out the image suffix."""
    if not isinstance(name, str) or not name:
        raise UslError(f"{where}: file path {name!r} is not a string")
    path = folder / name
    if path.is_file():
        return path
    for suffix in IMAGE_SUFFIXES if not path.suffix else ():
        if path.with_name(path.name + suffix).is_file():
            return path.with_name(path.name + suffix)
    raise UslError(f"{where}: {path}: no such file")


def camera_to_world(value: Any, where: str) -> np.ndarray:
    """``transform_matrix`` (4x4 or 3x4, OpenGL axes) -> 4x4 camera-to-world in OpenCV axes."""
    try:
        matrix = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        matrix = np.zeros(0)
    if matrix.shape not in ((4, 4), (3, 4)) or not np.isfinite(matrix).all():
        raise UslError(f"{where}: transform_matrix is not a finite 4x4 matrix")
    pose = np.eye(4)
    pose[:3] = matrix[:3]
    return pose @ OPENGL_TO_OPENCV


def read_transforms(path: Path) -> PosedCapture:
    """Every frame of ``transforms.json``, in file-name order (frame numbers are time order)."""
    data = load_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list) or not data["frames"]:
        raise UslError(f"{path}: not a capture's transforms.json (no non-empty 'frames' list)")
    folder = path.parent
    unit = _number({}, data, "depth_unit_scale_factor", str(path), MILLIMETRES)
    if unit <= 0:
        raise UslError(f"{path}: depth_unit_scale_factor must be > 0, got {unit}")
    entries = []
    for k, entry in enumerate(data["frames"]):
        if not isinstance(entry, dict) or "file_path" not in entry:
            raise UslError(f"{path}: frame {k} is not an object with a file_path")
        where = f"{path}: frame {k} ({entry['file_path']})"
        if "transform_matrix" not in entry:
            raise UslError(f"{where}: no pose (transform_matrix)")
        entries.append((str(entry["file_path"]), entry, where))
    entries.sort(key=lambda e: natural_key(e[0]))
    frames = []
    for index, (_, entry, where) in enumerate(entries):
        image = existing_file(folder, entry["file_path"], where)
        depth = existing_file(folder, entry["depth_file_path"], where) if "depth_file_path" in entry else None
        frames.append(
            CaptureFrame(
                index,
                Path(os.path.relpath(image, folder)).as_posix(),
                image,
                frame_camera(entry, data, where),
                camera_to_world(entry["transform_matrix"], where),
                depth,
            )
        )
    return PosedCapture(frames, TRANSFORMS, depth_unit=unit, metric=True)
