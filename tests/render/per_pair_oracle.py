"""The dynamic renderer's former per-(object, view) implementation, kept as a test oracle for the
batched one: one summed-area table, one ``tolist`` and ~47 small ops per pair."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from usl.metrics.boxes import masks_to_boxes
from usl.render.dynamic import (
    DynamicRender,
    _cells_inside_image,
    _empty_boxes,
    _empty_if_degenerate,
    _union,
    projected_boxes,
    square_windows,
    window_intrinsics,
)
from usl.render.screen import project_faces
from usl.render.soft import SoftRasterSettings, rasterize_soft

Tensor = torch.Tensor


def resample_mask_area(mask: Tensor, window: Sequence[float], resolution: int) -> Tensor:
    """Coverage (resolution, resolution) float64 in [0, 1] of ``mask`` (H, W) over one ``window``."""
    height, width = mask.shape
    x0, y0, x1, y1 = (float(v) for v in window)
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
    iy = ys.floor().long().clamp(max=table.shape[0] - 2)
    ix = xs.floor().long().clamp(max=table.shape[1] - 2)
    fy, fx = (ys - iy)[:, None], (xs - ix)[None, :]
    iy, ix = iy[:, None], ix[None, :]
    top = table[iy, ix] * (1 - fx) + table[iy, ix + 1] * fx
    bottom = table[iy + 1, ix] * (1 - fx) + table[iy + 1, ix + 1] * fx
    return top * (1 - fy) + bottom * fy


def mask_boxes(masks: Sequence[Tensor]) -> Tensor:
    boxes = torch.cat([masks_to_boxes(m.unsqueeze(0)) for m in masks]).to(torch.float64)
    empty = boxes.isnan().any(dim=1, keepdim=True)
    return torch.where(empty, _empty_boxes(boxes.shape[0], boxes.device), boxes)


def render_dynamic_per_pair(
    verts: Tensor,
    faces: Tensor,
    face_window: Tensor,
    K: Tensor,
    true_masks: Sequence[Tensor],
    resolution: int = 72,
    settings: SoftRasterSettings = SoftRasterSettings(),
    padding: float = 0.05,
    min_size: float = 4.0,
    true_boxes: Tensor | None = None,
    ignore_masks: Sequence[Tensor] | None = None,
) -> DynamicRender:
    faces, face_window = faces.long(), face_window.long()
    image_sizes = torch.tensor([tuple(m.shape[-2:]) for m in true_masks], dtype=torch.float64, device=K.device)
    with torch.no_grad():
        truth = mask_boxes(true_masks) if true_boxes is None else _empty_if_degenerate(true_boxes.to(torch.float64))
        boxes = _union(truth.to(K.device), projected_boxes(verts, faces, face_window, K, settings.near))
        windows = square_windows(boxes, image_sizes, padding, min_size)
    K_window = window_intrinsics(windows, resolution).to(K.dtype) @ K
    soft = rasterize_soft(verts, faces, face_window, K_window, resolution, resolution, settings)
    target = torch.stack(
        [resample_mask_area(m, w.tolist(), resolution) for m, w in zip(true_masks, windows, strict=True)]
    )
    valid = _cells_inside_image(windows, image_sizes, resolution)
    if ignore_masks is not None:
        hidden = torch.stack(
            [resample_mask_area(m, w.tolist(), resolution) for m, w in zip(ignore_masks, windows, strict=True)]
        )
        valid = valid & (hidden <= 0.5).to(valid.device)
    return DynamicRender(
        soft=soft,
        target=target.to(device=soft.device, dtype=soft.dtype),
        valid=valid,
        windows=windows.to(K.dtype),
        K_window=K_window,
    )


def projected_boxes_of_kept_faces(verts: Tensor, faces: Tensor, face_window: Tensor, K: Tensor, near: float) -> Tensor:
    """The former ``projected_boxes``: culled faces dropped by boolean indexing (a device read)."""
    screen = project_faces(verts.detach(), faces, face_window, K.detach(), near)
    xy = screen.xy[screen.visible].to(torch.float64)
    owner = face_window[screen.visible]
    boxes = _empty_boxes(K.shape[0], K.device).clone()
    lo, hi = xy.amin(dim=1), xy.amax(dim=1)
    boxes[:, :2] = boxes[:, :2].scatter_reduce(0, owner[:, None].expand(-1, 2), lo, "amin")
    boxes[:, 2:] = boxes[:, 2:].scatter_reduce(0, owner[:, None].expand(-1, 2), hi, "amax")
    return boxes
