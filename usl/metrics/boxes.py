"""Box gIoU (paper Sec. 4: Box_2D gIoU of the boxes around predicted and true silhouettes)."""

from __future__ import annotations

import torch

Tensor = torch.Tensor


def box_giou(a: Tensor, b: Tensor, eps: float = 1e-9) -> Tensor:
    """Generalized IoU (Rezatofighi et al. 2019) of aligned xyxy boxes: (..., 4), (..., 4) -> (...).

    ``gIoU = IoU - |C \\ (A u B)| / |C|`` with C the smallest box enclosing A and B; in [-1, 1].
    Pairs are matched element-wise (broadcasting), not all-against-all.
    """
    area_a = (a[..., 2] - a[..., 0]).clamp(min=0) * (a[..., 3] - a[..., 1]).clamp(min=0)
    area_b = (b[..., 2] - b[..., 0]).clamp(min=0) * (b[..., 3] - b[..., 1]).clamp(min=0)
    lo = torch.maximum(a[..., :2], b[..., :2])
    hi = torch.minimum(a[..., 2:], b[..., 2:])
    inter = (hi - lo).clamp(min=0).prod(-1)
    union = area_a + area_b - inter
    hull = (torch.maximum(a[..., 2:], b[..., 2:]) - torch.minimum(a[..., :2], b[..., :2])).clamp(min=0).prod(-1)
    return inter / (union + eps) - (hull - union) / (hull + eps)


def masks_to_boxes(masks: Tensor) -> Tensor:
    """Tight xyxy boxes (..., 4) around binary masks (..., H, W) in the pixel frame of docs/design.md §2.

    Pixel (r, c) covers [c, c+1] x [r, r+1], so a single pixel at (r, c) gives
    [c, r, c + 1, r + 1]. Empty masks give NaN boxes.
    """
    fg = masks > 0.5 if masks.is_floating_point() else masks.bool()
    height, width = fg.shape[-2:]
    cols, rows = fg.any(-2), fg.any(-1)
    col_idx = torch.arange(width, device=fg.device, dtype=torch.float32)
    row_idx = torch.arange(height, device=fg.device, dtype=torch.float32)
    inf = float("inf")
    x0 = torch.where(cols, col_idx, inf).amin(-1)
    x1 = torch.where(cols, col_idx, -inf).amax(-1) + 1
    y0 = torch.where(rows, row_idx, inf).amin(-1)
    y1 = torch.where(rows, row_idx, -inf).amax(-1) + 1
    boxes = torch.stack([x0, y0, x1, y1], dim=-1)
    return torch.where(cols.any(-1, keepdim=True), boxes, float("nan"))
