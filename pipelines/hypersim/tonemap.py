"""Hypersim's own tone mapping (``code/python/tools/scene_generate_images_tonemap.py``).

Scale the linear image so the 90th percentile brightness of pixels with geometry maps to 0.8 after
gamma 1/2.2; brightness is CCIR601 YIQ luma. The scale comes from the full-resolution frame, so a
resized image gets the same exposure as the original; it is then applied to the (area-)resized
linear image, resizing in linear light as a camera would integrate it.
"""

from __future__ import annotations

import cv2
import numpy as np

GAMMA = 1.0 / 2.2
PERCENTILE = 90.0
TARGET_BRIGHTNESS = 0.8
MIN_PERCENTILE = 1e-4  # below this the scale is 0 (Hypersim's divide-by-zero guard)
LUMA = np.array([[0.3, 0.59, 0.11]], np.float32)  # CCIR601 YIQ brightness of (R, G, B)


def percentile(values: np.ndarray, q: float, count: int | None = None) -> float:
    """``np.percentile(values[:count], q)`` (linear interpolation) with one partial sort, where the
    ``count`` values that count are the smallest (the rest may be +inf placeholders)."""
    n = values.size if count is None else count
    position = q / 100.0 * (n - 1)
    low = int(np.floor(position))
    high = min(low + 1, n - 1)
    part = np.partition(values, [low, high])
    return float(part[low] + (position - low) * (float(part[high]) - float(part[low])))


def tonemap_scale(rgb: np.ndarray, valid: np.ndarray) -> float:
    """Exposure scale of one frame; ``valid`` marks pixels with geometry (render entity id != -1)."""
    brightness = cv2.transform(rgb, LUMA).reshape(-1)
    use = (valid & np.isfinite(brightness.reshape(valid.shape))).reshape(-1)
    count = int(np.count_nonzero(use))
    if count == 0:
        return 1.0
    current = percentile(np.where(use, brightness, np.float32(np.inf)), PERCENTILE, count)
    if current < MIN_PERCENTILE:
        return 0.0
    return TARGET_BRIGHTNESS ** (1.0 / GAMMA) / current


def apply_tonemap(rgb: np.ndarray, scale: float) -> np.ndarray:
    """``clip(max(scale * rgb, 0) ** (1/2.2), 0, 1)`` as rounded uint8; non-finite radiance -> 0."""
    x = rgb * np.float32(scale)
    np.fmax(x, 0.0, out=x)  # fmax: NaN -> 0
    np.minimum(x, 1.0, out=x)
    np.power(x, np.float32(GAMMA), out=x)
    return cv2.convertScaleAbs(x, alpha=255.0)  # rounds to nearest and saturates
