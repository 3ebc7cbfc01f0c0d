"""Mask IoU (paper Sec. 4: Mask_2D IoU of the rendered prediction vs. the true mask)."""

from __future__ import annotations

import torch

Tensor = torch.Tensor


def mask_iou(pred: Tensor, true: Tensor, empty_value: float = 0.0) -> Tensor:
    """IoU of aligned dense binary masks, batched over leading dims: (..., H, W) -> (...).

    Inputs are bool (or values > 0.5 count as foreground). Where both masks are empty the
    IoU is ``empty_value`` (0 by default, as pycocotools); pass ``float("nan")`` to mark
    such pairs for exclusion with ``nanmean``.
    """
    if pred.shape != true.shape:
        raise ValueError(f"mask_iou: pred {tuple(pred.shape)} and true {tuple(true.shape)} differ")
    p, t = _binary(pred).flatten(-2), _binary(true).flatten(-2)
    inter = (p & t).sum(-1)
    union = (p | t).sum(-1)
    iou = inter.double() / union.clamp(min=1).double()
    return torch.where(union > 0, iou, torch.full_like(iou, empty_value)).float()


def _binary(mask: Tensor) -> Tensor:
    return mask > 0.5 if mask.is_floating_point() else mask.bool()
