"""Exact-area resampling of binary masks into axis-aligned windows.

A window cell's value is the fraction of its area covered by true-mask pixels, each pixel
taken as the unit square it occupies in the pixel frame (docs/design.md §2). This is exact for
any fractional window, up- or downsampling alike, with no aliasing: the continuous
integral of a piecewise-constant mask is the bilinear interpolation of its summed-area
table at the cell corners. Area outside the image counts as uncovered.

All P windows are resampled at once: one integer summed-area table per mask (exact counts),
sampled at every window's (R + 1)^2 cell corners with one gather, so the cost in ops does not
grow with P and nothing is read back to the host. On the CPU (with numba) a compiled loop does the
same arithmetic mask by mask (:mod:`usl.utils.compiled`): no table of all masks, no gathered
corner tensors.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from usl.utils.compiled import compiled, serves

Tensor = torch.Tensor


def resample_masks_area(masks: Tensor, windows: Tensor, resolution: int) -> Tensor:
    """Coverage (P, R, R) float64 in [0, 1] of each mask (P, H, W) over its window (P, 4).

    ``windows`` are [x0, y0, x1, y1] in the masks' pixel frame with x1 > x0 and y1 > y0; they may
    extend past the image.
    """
    windows = windows.to(device=masks.device, dtype=torch.float64)
    if serves(masks):
        out = np.empty((masks.shape[0], resolution, resolution), dtype=np.float64)
        height, width = masks.shape[1:]
        _area_loop(
            masks.numpy().astype(np.uint8, copy=False),
            windows.numpy(),
            np.empty((height + 1, width + 1), dtype=np.int32),
            np.empty((resolution + 1, resolution + 1), dtype=np.float64),
            out,
        )
        return torch.from_numpy(out)
    return _torch_resample_masks_area(masks, windows, resolution)


def _torch_resample_masks_area(masks: Tensor, windows: Tensor, resolution: int) -> Tensor:
    num, height, width = masks.shape
    table = torch.zeros(num, height + 1, width + 1, dtype=torch.int32, device=masks.device)
    table[:, 1:, 1:] = masks.to(torch.int32).cumsum(1, dtype=torch.int32).cumsum(2, dtype=torch.int32)
    steps = torch.arange(resolution + 1, dtype=torch.float64, device=masks.device) / resolution
    x0, y0, x1, y1 = windows.unbind(1)
    ex = (x0[:, None] + steps * (x1 - x0)[:, None]).clamp(0, width)  # (P, R + 1) cell edges
    ey = (y0[:, None] + steps * (y1 - y0)[:, None]).clamp(0, height)
    integral = _bilinear_on_grids(table, ey, ex)
    cells = integral[:, 1:, 1:] - integral[:, :-1, 1:] - integral[:, 1:, :-1] + integral[:, :-1, :-1]
    cell_area = (x1 - x0) * (y1 - y0) / resolution**2
    return (cells / cell_area[:, None, None]).clamp(0.0, 1.0)


def _bilinear_on_grids(table: Tensor, ys: Tensor, xs: Tensor) -> Tensor:
    """Bilinear interpolation of each table (P, H + 1, W + 1) (integer-corner samples) at its grid ys x xs."""
    num, rows, cols = table.shape
    iy = ys.floor().long().clamp(max=rows - 2)  # (P, R + 1)
    ix = xs.floor().long().clamp(max=cols - 2)
    fy, fx = (ys - iy)[:, :, None], (xs - ix)[:, None, :]
    base = (
        (torch.arange(num, device=table.device) * rows * cols)[:, None, None] + iy[:, :, None] * cols + ix[:, None, :]
    )
    flat = table.reshape(-1)
    corners = [flat[base + offset].to(torch.float64) for offset in (0, 1, cols, cols + 1)]
    top = corners[0] * (1 - fx) + corners[1] * fx
    bottom = corners[2] * (1 - fx) + corners[3] * fx
    return top * (1 - fy) + bottom * fy


@compiled
def _area_loop(masks, windows, table, integral, out):  # pragma: no cover
    """:func:`_torch_resample_masks_area` mask by mask, op for op in float64: the summed-area
    ``table`` (H + 1, W + 1) and the ``integral`` (R + 1, R + 1) at the cell corners are scratch."""
    height, width = masks.shape[1], masks.shape[2]
    resolution = out.shape[1]
    zero, one = np.float64(0.0), np.float64(1.0)
    for p in range(masks.shape[0]):
        for col in range(width + 1):
            table[0, col] = 0
        for row in range(height):
            table[row + 1, 0] = 0
            run = 0
            for col in range(width):
                run += masks[p, row, col]
                table[row + 1, col + 1] = table[row, col + 1] + run
        x0, y0, x1, y1 = windows[p, 0], windows[p, 1], windows[p, 2], windows[p, 3]
        for i in range(resolution + 1):
            y = y0 + (i / resolution) * (y1 - y0)
            y = min(max(y, zero), np.float64(height))
            iy = min(int(math.floor(y)), height - 1)
            fy = y - iy
            for j in range(resolution + 1):
                x = x0 + (j / resolution) * (x1 - x0)
                x = min(max(x, zero), np.float64(width))
                ix = min(int(math.floor(x)), width - 1)
                fx = x - ix
                top = table[iy, ix] * (one - fx) + table[iy, ix + 1] * fx
                bottom = table[iy + 1, ix] * (one - fx) + table[iy + 1, ix + 1] * fx
                integral[i, j] = top * (one - fy) + bottom * fy
        cell_area = (x1 - x0) * (y1 - y0) / (resolution * resolution)
        for i in range(resolution):
            for j in range(resolution):
                cell = integral[i + 1, j + 1] - integral[i, j + 1] - integral[i + 1, j] + integral[i, j]
                out[p, i, j] = min(max(cell / cell_area, zero), one)
