"""What every capture reader returns: frames with cameras and poses, before metric scale is known."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .camera import FrameCamera

# 16-bit depth images store millimetres unless the format says otherwise (nerfstudio's
# depth_unit_scale_factor)
MILLIMETRES = 1e-3
# nerfstudio / instant-ngp / OpenGL camera axes (x right, y up, looking down -z) -> OpenCV (y down, +z)
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


@dataclass(frozen=True)
class CaptureFrame:
    index: int  # time order within the capture; the records' view_id (gaps: frames without a pose)
    name: str  # the image's path relative to the capture folder, as detections name it
    image: Path
    camera: FrameCamera
    cam_to_world: np.ndarray  # 4x4, OpenCV axes, the source's length unit
    depth: Path | None = None  # 16-bit depth image registered to the colour image (any resolution)


@dataclass
class SfmPoints:
    """Sparse points seen by each frame (COLMAP models): what ties the source's unit to depth maps."""

    uv: dict[int, np.ndarray] = field(default_factory=dict)  # frame index -> (N, 2) pixels of the raw image
    z: dict[int, np.ndarray] = field(default_factory=dict)  # frame index -> (N,) camera-space depth, source unit


@dataclass
class PosedCapture:
    frames: list[CaptureFrame]
    pose_source: str  # e.g. "transforms.json", "colmap model sparse/0", "sfm (pycolmap)"
    depth_unit: float = MILLIMETRES  # metres per stored depth value
    metric: bool = False  # the source's poses are already in metres (capture apps' transforms.json)
    points: SfmPoints | None = None
    unposed: list[str] = field(default_factory=list)  # images without a pose (e.g. not registered by SfM)


def natural_key(name: str) -> list[object]:
    """Sort key putting frame_2 before frame_10: capture tools number frames without padding too."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]
