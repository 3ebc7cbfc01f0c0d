"""Reading a COLMAP model (``sparse/0`` or nerfstudio's ``colmap/sparse/0``, binary or text) via pycolmap.

COLMAP stores world-to-camera poses (``qvec``, ``tvec``, OpenCV axes) in its own arbitrary unit and
puts pixel centres at +0.5 like usl. Images live in ``<capture>/images/`` (COLMAP's ``image_path``);
depth images, when a capture has them, in ``<capture>/depth/`` under the image's name with ``.png``.
The sparse points each image sees are kept: they tie the model's unit to the depth maps (``scale``).
pycolmap is imported here only (``pip install usl[captures]``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from usl.errors import UslError

from .camera import FrameCamera
from .posed import CaptureFrame, PosedCapture, SfmPoints, natural_key

MODEL_DIRS = ("sparse/0", "colmap/sparse/0")
IMAGES_DIR = "images"
DEPTH_DIR = "depth"
IMAGE_SUFFIXES = {".jpg", ".jpeg", ".png"}
# COLMAP camera model -> (fx, fy, cx, cy, k1, k2, p1, p2) from its parameter list
CAMERA_MODELS = {
    "SIMPLE_PINHOLE": lambda p: (p[0], p[0], p[1], p[2], 0.0, 0.0, 0.0, 0.0),
    "PINHOLE": lambda p: (p[0], p[1], p[2], p[3], 0.0, 0.0, 0.0, 0.0),
    "SIMPLE_RADIAL": lambda p: (p[0], p[0], p[1], p[2], p[3], 0.0, 0.0, 0.0),
    "RADIAL": lambda p: (p[0], p[0], p[1], p[2], p[3], p[4], 0.0, 0.0),
    "OPENCV": lambda p: tuple(p[:8]),
}


def import_pycolmap() -> Any:
    try:
        import pycolmap
    except ImportError:
        raise UslError("reading COLMAP models and --poses sfm need pycolmap: pip install 'usl[captures]'") from None
    return pycolmap


def find_model(capture: Path) -> Path | None:
    """The capture's COLMAP model folder, if it has one."""
    for name in MODEL_DIRS:
        folder = capture / name
        if any((folder / f"cameras.{ext}").is_file() for ext in ("bin", "txt")):
            return folder
    return None


def image_names(images: Path) -> list[str]:
    """Image files under ``images`` (recursively, as COLMAP reads them), relative, in frame order."""
    names = [p.relative_to(images).as_posix() for p in images.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES]
    return sorted(names, key=natural_key)


def frame_camera(camera: Any, where: str) -> FrameCamera:
    model = camera.model_name if hasattr(camera, "model_name") else str(camera.model.name)
    if model not in CAMERA_MODELS:
        raise UslError(f"{where}: camera {camera.camera_id} is a {model} camera; supported: {', '.join(CAMERA_MODELS)}")
    fx, fy, cx, cy, k1, k2, p1, p2 = (float(v) for v in CAMERA_MODELS[model](list(camera.params)))
    return FrameCamera(int(camera.width), int(camera.height), (fx, fy, cx, cy), (k1, k2, p1, p2, 0.0))


def read_model(model: Path) -> Any:
    pycolmap = import_pycolmap()
    reconstruction = pycolmap.Reconstruction()
    try:
        reconstruction.read(str(model))
    except Exception as exc:  # pycolmap raises its own (C++) errors for truncated or foreign files
        raise UslError(f"{model}: not a readable COLMAP model ({type(exc).__name__}: {exc})") from None
    return reconstruction


def posed_from_reconstruction(
    reconstruction: Any, images: Path, capture: Path, source: str, names: list[str], where: str
) -> PosedCapture:
    """Frames of ``names`` (all images of the capture, in order) with the poses the model gives."""
    by_name = {image.name: image for image in reconstruction.images.values() if image.has_pose}
    unknown = sorted(set(by_name) - set(names))
    if unknown:
        raise UslError(f"{where}: image {unknown[0]} is not in {images} ({len(unknown)} such)")
    frames, points, unposed = [], SfmPoints(), []
    xyz = {pid: np.asarray(p.xyz, dtype=np.float64) for pid, p in reconstruction.points3D.items()}
    for index, name in enumerate(names):
        image = by_name.get(name)
        if image is None:
            unposed.append(name)
            continue
        world_to_cam = np.eye(4)
        world_to_cam[:3] = np.asarray(image.cam_from_world().matrix(), dtype=np.float64)
        depth = (capture / DEPTH_DIR / name).with_suffix(".png")
        frames.append(
            CaptureFrame(
                index,
                (images / name).relative_to(capture).as_posix() if images.is_relative_to(capture) else name,
                images / name,
                frame_camera(reconstruction.cameras[image.camera_id], where),
                np.linalg.inv(world_to_cam),
                depth if depth.is_file() else None,
            )
        )
        seen = [(p.xy, xyz[p.point3D_id]) for p in image.points2D if p.has_point3D()]
        if seen:
            uv = np.array([s[0] for s in seen], dtype=np.float64)
            cam = np.array([s[1] for s in seen]) @ world_to_cam[:3, :3].T + world_to_cam[:3, 3]
            points.uv[index], points.z[index] = uv, cam[:, 2]
    if not frames:
        raise UslError(f"{where}: no image has a pose")
    return PosedCapture(frames, source, points=points, unposed=unposed)


def read_colmap(capture: Path, model: Path) -> PosedCapture:
    """The capture's COLMAP model, with its images in ``<capture>/images``."""
    images = capture / IMAGES_DIR
    if not images.is_dir():
        raise UslError(f"{images}: no such folder (the images of the COLMAP model {model})")
    names = image_names(images)
    source = f"colmap model {model.relative_to(capture).as_posix()}"
    return posed_from_reconstruction(read_model(model), images, capture, source, names, str(model))
