"""The output pixel grid of a scan: its K, and resampling of colour, depth and masks onto it.

Everything downstream of reading (tracking, warping, records) works in this one grid. Colour and
masks share the colour camera, so they resample by a pure scale. Depth is registered to the colour
camera (same centre and orientation, its own intrinsics), so output pixel -> depth pixel is the
homography ``K_depth @ inv(K_out)``, with planar depth unchanged: one nearest-neighbour lookup table
per scan, computed once with the project/unproject of ``usl.geometry.cameras``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from usl.geometry.cameras import project, scale_intrinsics, unproject
from usl.records import encode_image

from .scan import Calibration, Scan


def pixel_centres(width: int, height: int) -> np.ndarray:
    """(H*W, 2) continuous (u, v) of every pixel centre, row-major (docs/design.md §2: +0.5)."""
    v, u = np.mgrid[0:height, 0:width]
    return np.stack([u.ravel() + 0.5, v.ravel() + 0.5], axis=1)


def nearest_index(src_uv: np.ndarray, width: int, height: int) -> np.ndarray:
    """Flat index of the source pixel containing each continuous (u, v); -1 outside the image."""
    col = np.floor(src_uv[:, 0]).astype(np.int64)
    row = np.floor(src_uv[:, 1]).astype(np.int64)
    inside = (col >= 0) & (col < width) & (row >= 0) & (row < height) & np.isfinite(src_uv).all(axis=1)
    return np.where(inside, row * width + col, -1)


def centre_source_index(n_out: int, n_src: int) -> np.ndarray:
    """Index of the source pixel under each output pixel centre when n_src pixels span n_out (exact)."""
    return ((2 * np.arange(n_out, dtype=np.int64) + 1) * n_src) // (2 * n_out)


def resample_nearest(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """Nearest-neighbour resize of a 2D array sampling at pixel centres (docs/design.md §2)."""
    h, w = image.shape
    if (h, w) == (height, width):
        return image
    return image[:, centre_source_index(width, w)][centre_source_index(height, h)]


@dataclass
class OutputGrid:
    width: int
    height: int
    K: np.ndarray  # 3x3 for this grid, pixel centres at +0.5
    color_size: tuple[int, int]
    depth_index: np.ndarray  # (H*W,) flat index into the depth image, -1 where depth does not cover

    @classmethod
    def for_scan(cls, calibration: Calibration, size: tuple[int, int] | None) -> OutputGrid:
        """The grid of ``size`` (width, height), or of the colour camera when ``size`` is None."""
        cw, ch = calibration.color_size
        width, height = size if size is not None else (cw, ch)
        K = scale_intrinsics(torch.as_tensor(calibration.K_color), width / cw, height / ch).numpy()
        rays = unproject(
            torch.as_tensor(pixel_centres(width, height)),
            torch.ones(width * height, dtype=torch.float64),
            torch.as_tensor(K),
        )
        uv_depth, _ = project(rays, torch.as_tensor(calibration.K_depth))
        dw, dh = calibration.depth_size
        return cls(width, height, K, (cw, ch), nearest_index(uv_depth.numpy(), dw, dh))

    def __post_init__(self) -> None:
        self.depth_is_identity = bool(np.array_equal(self.depth_index, np.arange(self.width * self.height)))

    @property
    def size(self) -> tuple[int, int]:
        return self.width, self.height

    def depth(self, depth: np.ndarray | None) -> np.ndarray | None:
        """Depth (metres, NaN unknown) at the depth camera's resolution -> this grid."""
        if depth is None:
            return None
        if self.depth_is_identity:
            return depth
        flat = np.append(depth.ravel(), np.float32(np.nan))  # index -1 reads the NaN
        return flat[self.depth_index].reshape(self.height, self.width)

    def mask(self, mask: np.ndarray) -> np.ndarray:
        """A mask over the colour frame (any resolution) -> this grid, nearest at pixel centres.

        Colour and masks share the colour camera, so this is a pure scale: each grid pixel takes the
        source pixel under its centre. Columns go first, which suits pycocotools' column-major arrays.
        """
        return resample_nearest(mask, self.height, self.width)

    def to_frame(self, mask: np.ndarray, height: int, width: int) -> np.ndarray:
        """The inverse direction: a mask on this grid -> a (height, width) mask over the colour frame."""
        return resample_nearest(mask, height, width)

    def image(self, scan: Scan, index: int, jpeg_quality: int) -> bytes:
        """The frame's encoded image on this grid: the stored bytes untouched when no resize is needed."""
        if self.size == scan.color_size:
            encoded = scan.color_encoded(index)
            if encoded is not None:
                return encoded
        rgb = scan.color(index)
        if self.size != scan.color_size:
            rgb = cv2.resize(rgb, self.size, interpolation=cv2.INTER_AREA)
        return encode_image(np.ascontiguousarray(rgb), "jpeg", jpeg_quality)
