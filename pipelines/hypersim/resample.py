"""Resizing a frame's images consistently with ``cameras.scale_intrinsics`` (pure scale of the
+0.5-centred pixel frame): output pixel (j, i) looks at source position ((j+.5) W/w, (i+.5) H/h).

* colour: area average in linear light (exact footprint of each output pixel);
* labels: the source pixel under that position (nearest; labels cannot be averaged);
* planar depth: bilinear interpolation, at that position, of ``g = r_z / z`` where ``r_z`` is the
  z component of the ray ``K^-1 [x, y, 1]``. On any plane ``g`` is affine in pixel coordinates, for
  any projective K (it is 1/w, the inverse homogeneous divisor; for an upper-triangular K simply
  1/z), so the interpolation is exact on planes, tilt-shift cameras included. It is used only where
  the four source neighbours are "flat": ``g`` has near-zero second differences around each of them,
  which planes at any slant pass and depth edges, creases and unknown pixels fail. Elsewhere the
  nearest source pixel is kept, so no "flying pixels" appear between objects.
"""

from __future__ import annotations

import cv2
import numpy as np

# |second difference of g| / g above which a source pixel is not on a plane. Float16
# distances bring up to ~2e-3; a depth step of 1% or more exceeds 1e-2.
FLATNESS_TOL = 5e-3


def _nearest(size_in: int, size_out: int) -> np.ndarray:
    centres = (np.arange(size_out) + 0.5) * (size_in / size_out)
    return np.minimum(np.floor(centres).astype(np.int64), size_in - 1)


def _linear(size_in: int, size_out: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    position = (np.arange(size_out) + 0.5) * (size_in / size_out) - 0.5
    low = np.floor(position)
    weight = (position - low).astype(np.float32)
    low = low.astype(np.int64)
    return np.clip(low, 0, size_in - 1), np.clip(low + 1, 0, size_in - 1), weight


class Resampler:
    """Maps (H, W) source images to (h, w); the identity when the sizes agree. ``K``: the source
    image's intrinsics (only its inverse's last row matters, for depth)."""

    def __init__(self, width: int, height: int, out_width: int, out_height: int, K: np.ndarray):
        self.size_in = (width, height)
        self.size_out = (out_width, out_height)
        self.identity = self.size_in == self.size_out
        # Flat indices into the source image (np.take is ~3x faster than 2-D fancy indexing).
        rows, cols = _nearest(height, out_height), _nearest(width, out_width)
        self._nearest = rows[:, None] * width + cols[None, :]
        y0, y1, wy = _linear(height, out_height)
        x0, x1, wx = _linear(width, out_width)
        self._corners = [y[:, None] * width + x[None, :] for y in (y0, y1) for x in (x0, x1)]
        self._wy, self._wx = wy[:, None], wx[None, :]
        a, b, c = np.linalg.inv(K)[2]
        self._ray_z_in = _ray_z(a, b, c, width, height, width, height)
        self._ray_z_out = _ray_z(a, b, c, width, height, out_width, out_height)

    def labels(self, image: np.ndarray) -> np.ndarray:
        return image if self.identity else np.take(np.ascontiguousarray(image).ravel(), self._nearest)

    def colour(self, rgb: np.ndarray) -> np.ndarray:
        return rgb if self.identity else cv2.resize(rgb, self.size_out, interpolation=cv2.INTER_AREA)

    def depth(self, planar: np.ndarray) -> np.ndarray:
        """Planar depth (NaN unknown) at the output pixel centres."""
        if self.identity:
            return planar
        with np.errstate(divide="ignore", invalid="ignore"):
            g = self._ray_z_in / planar
            flat = _flat(g).ravel()
            smooth = np.logical_and.reduce([np.take(flat, index) for index in self._corners])
            q00, q01, q10, q11 = (np.take(g.ravel(), index) for index in self._corners)
            top = q00 + (q01 - q00) * self._wx
            bottom = q10 + (q11 - q10) * self._wx
            interpolated = self._ray_z_out / (top + (bottom - top) * self._wy)
        return np.where(smooth, interpolated, self.labels(planar)).astype(np.float32)


def _ray_z(a: float, b: float, c: float, width: int, height: int, out_width: int, out_height: int) -> np.ndarray:
    """``r_z = a x + b y + c`` at the output pixel centres, in source pixel coordinates (float32)."""
    x = (np.arange(out_width) + 0.5) * (width / out_width)
    y = (np.arange(out_height) + 0.5) * (height / out_height)
    return (a * x[None, :] + b * y[:, None] + c).astype(np.float32)


_SECOND_DIFFERENCE = np.array([[1.0, -2.0, 1.0]], np.float32)


def _flat(g: np.ndarray) -> np.ndarray:
    """Source pixels where ``g`` is affine (to FLATNESS_TOL) along their row and column
    neighbourhoods; border pixels are judged along the border only (no neighbour beyond it)."""
    g = np.ascontiguousarray(g, dtype=np.float32)
    along_x = np.abs(cv2.filter2D(g, -1, _SECOND_DIFFERENCE, borderType=cv2.BORDER_REPLICATE))
    along_y = np.abs(cv2.filter2D(g, -1, _SECOND_DIFFERENCE.T, borderType=cv2.BORDER_REPLICATE))
    along_x[:, [0, -1]] = 0.0
    along_y[[0, -1], :] = 0.0
    limit = np.float32(FLATNESS_TOL) * g
    return (along_x <= limit) & (along_y <= limit)
