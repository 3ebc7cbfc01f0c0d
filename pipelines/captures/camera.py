"""A capture's cameras, and resampling every frame onto one undistorted pinhole camera.

Capture formats give intrinsics per capture or per frame, with or without lens distortion
(nerfstudio's ``OPENCV`` ``k1 k2 p1 p2``, COLMAP's ``SIMPLE_RADIAL`` / ``OPENCV``). Records hold one
pinhole ``K`` per frame, and the tracker, the depth warp and the output grid of the ScanNet pipeline
work with one camera per scene; so a frame whose camera differs from the capture's reference camera
(the median of the frames' intrinsics, no distortion) is remapped onto it with OpenCV: bilinear for
colour, nearest for depth and masks. Frames already on the reference camera are left untouched.

All ``K`` here put pixel centres at +0.5 (docs/design.md §2), as nerfstudio and COLMAP do; OpenCV
puts them at integers, so its matrices are shifted by -0.5 on the way in.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

NO_DISTORTION = (0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class FrameCamera:
    """A frame's camera: ``K`` (3x3, pixel centres at +0.5) at ``width`` x ``height``, OpenCV
    distortion ``(k1, k2, p1, p2, k3)``."""

    width: int
    height: int
    K: tuple[float, float, float, float]  # fx, fy, cx, cy
    distortion: tuple[float, float, float, float, float] = NO_DISTORTION

    @property
    def size(self) -> tuple[int, int]:
        return self.width, self.height

    def matrix(self, width: int | None = None, height: int | None = None) -> np.ndarray:
        """3x3 K, scaled to ``width`` x ``height`` (the depth image's size, say) when given."""
        sx = 1.0 if width is None else width / self.width
        sy = 1.0 if height is None else height / self.height
        fx, fy, cx, cy = self.K
        return np.array([[fx * sx, 0.0, cx * sx], [0.0, fy * sy, cy * sy], [0.0, 0.0, 1.0]])


def reference_camera(cameras: list[FrameCamera]) -> FrameCamera:
    """The capture's one pinhole camera: the median intrinsics of its frames, without distortion."""
    K = np.median(np.array([c.K for c in cameras], dtype=np.float64), axis=0)
    return FrameCamera(cameras[0].width, cameras[0].height, tuple(float(v) for v in K))


def _opencv(K: np.ndarray) -> np.ndarray:
    return K - np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 0.5], [0.0, 0.0, 0.0]])


@dataclass
class Rectifier:
    """Remaps images of one frame camera onto the reference camera (maps cached per image size)."""

    camera: FrameCamera
    reference: FrameCamera
    _maps: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    @property
    def identity(self) -> bool:
        return self.camera.K == self.reference.K and not any(self.camera.distortion)

    def _map(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        if (width, height) not in self._maps:
            self._maps[width, height] = cv2.initUndistortRectifyMap(
                _opencv(self.camera.matrix(width, height)),
                np.array(self.camera.distortion, dtype=np.float64),
                None,
                _opencv(self.reference.matrix(width, height)),
                (width, height),
                cv2.CV_32FC1,
            )
        return self._maps[width, height]

    def image(self, rgb: np.ndarray) -> np.ndarray:
        if self.identity:
            return rgb
        height, width = rgb.shape[:2]
        return cv2.remap(rgb, *self._map(width, height), cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)

    def nearest(self, values: np.ndarray, outside: float) -> np.ndarray:
        """Depth (float, ``outside`` = NaN) or a mask (uint8, ``outside`` = 0), at any resolution."""
        if self.identity:
            return values
        height, width = values.shape
        return cv2.remap(
            values, *self._map(width, height), cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=outside
        )
