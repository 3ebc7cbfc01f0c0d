"""Nearest-depth L1 (paper Sec. 4: |true - predicted| nearest depth of each object)."""

from __future__ import annotations

import torch

Tensor = torch.Tensor


def nearest_depth(depth: Tensor, mask: Tensor) -> Tensor:
    """Smallest positive depth inside each mask: (..., H, W), (..., H, W) -> (...).

    ``depth`` is a depth map (0 or NaN = unknown, e.g. a rendered z-buffer's background or
    a sensor hole) and ``mask`` the object's silhouette in the same view. Objects without
    any known depth pixel get NaN, matching the records' ``depth_min`` convention.
    """
    fg = mask > 0.5 if mask.is_floating_point() else mask.bool()
    known = fg & (depth > 0)  # NaN compares False
    return torch.where(known, depth, float("inf")).flatten(-2).amin(-1).where(known.flatten(-2).any(-1), float("nan"))


def depth_l1(pred: Tensor, true: Tensor) -> Tensor:
    """Per-object absolute error |pred - true| of nearest depths; NaN where either is unknown.

    Average with ``torch.nanmean`` so objects without depth are left out.
    """
    return (pred - true).abs()
