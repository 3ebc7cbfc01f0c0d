"""Exact-area resampling of binary masks into axis-aligned windows.

A window cell's value is the fraction of its area covered by true-mask pixels, each pixel
taken as the unit square it occupies in the pixel frame (docs/design.md §2). This is exact for
any fractional window, up- or downsampling alike, with no aliasing: the continuous
integral of a piecewise-constant mask is the bilinear interpolation of its summed-area
table at the cell corners. Area outside the image counts as uncovered.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

Tensor = torch.Tensor


def resample_mask_area(mask: Tensor, window: Sequence[float], resolution: int) -> Tensor:
    """Coverage (resolution, resolution) float64 in [0, 1] of ``mask`` (H, W) over ``window``.

    ``window`` is [x0, y0, x1, y1] in the mask's pixel frame (may extend past the image).
    """
    height, width = mask.shape
    x0, y0, x1, y1 = (float(v) for v in window)
    if not (x1 > x0 and y1 > y0):
        raise ValueError(f"resample_mask_area: window must have x1 > x0 and y1 > y0, got {[x0, y0, x1, y1]}")
    out = torch.zeros(resolution, resolution, dtype=torch.float64, device=mask.device)
    c0, c1 = max(0, math.floor(x0)), min(width, math.ceil(x1))
    r0, r1 = max(0, math.floor(y0)), min(height, math.ceil(y1))
    if c1 <= c0 or r1 <= r0:
        return out
    crop = mask[r0:r1, c0:c1].to(torch.float64)
    table = torch.zeros(r1 - r0 + 1, c1 - c0 + 1, dtype=torch.float64, device=mask.device)
    table[1:, 1:] = crop.cumsum(0).cumsum(1)
    ex = torch.linspace(x0, x1, resolution + 1, dtype=torch.float64, device=mask.device) - c0
    ey = torch.linspace(y0, y1, resolution + 1, dtype=torch.float64, device=mask.device) - r0
    integral = _bilinear_on_grid(table, ey.clamp(0, r1 - r0), ex.clamp(0, c1 - c0))
    cells = integral[1:, 1:] - integral[:-1, 1:] - integral[1:, :-1] + integral[:-1, :-1]
    cell_area = (x1 - x0) * (y1 - y0) / resolution**2
    return (cells / cell_area).clamp(0.0, 1.0)


def _bilinear_on_grid(table: Tensor, ys: Tensor, xs: Tensor) -> Tensor:
    """Bilinear interpolation of ``table`` (integer-corner samples) at the grid ys x xs."""
    iy = ys.floor().long().clamp(max=table.shape[0] - 2)
    ix = xs.floor().long().clamp(max=table.shape[1] - 2)
    fy, fx = (ys - iy)[:, None], (xs - ix)[None, :]
    iy, ix = iy[:, None], ix[None, :]
    top = table[iy, ix] * (1 - fx) + table[iy, ix + 1] * fx
    bottom = table[iy + 1, ix] * (1 - fx) + table[iy + 1, ix + 1] * fx
    return top * (1 - fy) + bottom * fy
