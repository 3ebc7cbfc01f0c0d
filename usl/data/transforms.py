"""Resizing views consistently: image, masks, boxes and the intrinsics move together.

With pixel centres at +0.5 (docs/design.md §2) an image resized by (sx, sy) is a pure scale of
the pixel frame, so boxes scale and ``K' = diag(sx, sy, 1) K`` (``cameras.scale_intrinsics``).
Masks use ``nearest-exact`` (sampling at pixel centres), which agrees with that convention.
"""
from __future__ import annotations

from dataclasses import replace

import torch
import torch.nn.functional as F

from usl.geometry.cameras import scale_intrinsics

from .frames import FrameData
from .samples import TargetView

Tensor = torch.Tensor


def resized_shape(height: int, width: int, max_size: int) -> tuple[int, int]:
    """(H', W') with the longer side at most ``max_size`` (0: unchanged); never upsamples."""
    if max_size <= 0 or max(height, width) <= max_size:
        return height, width
    scale = max_size / max(height, width)
    return max(1, round(height * scale)), max(1, round(width * scale))


def resize_masks(masks: Tensor, size: tuple[int, int]) -> Tensor:
    """(N, H, W) bool -> (N, H', W') bool by nearest pixel centre."""
    if tuple(masks.shape[-2:]) == tuple(size):
        return masks
    if masks.shape[0] == 0:
        return masks.new_zeros(0, *size)
    return F.interpolate(masks[None].to(torch.uint8), size=size, mode="nearest-exact")[0].bool()


def _scales(old: tuple[int, int], new: tuple[int, int]) -> tuple[float, float]:
    return new[1] / old[1], new[0] / old[0]  # (sx, sy)


def resize_frame(frame: FrameData, max_size: int) -> FrameData:
    """The input view at the training resolution."""
    old = frame.size
    new = resized_shape(*old, max_size)
    if new == old:
        return frame
    sx, sy = _scales(old, new)
    image = F.interpolate(frame.image[None], size=new, mode="bilinear", align_corners=False, antialias=True)[0]
    depth = frame.depth
    if depth is not None:
        depth = F.interpolate(depth[None, None], size=new, mode="nearest-exact")[0, 0]
    return replace(
        frame,
        image=image.clamp_(0.0, 1.0),
        K=scale_intrinsics(frame.K.double(), sx, sy).float(),
        boxes=frame.boxes * torch.tensor([sx, sy, sx, sy], dtype=frame.boxes.dtype),
        masks=resize_masks(frame.masks, new),
        depth=depth,
    )


def resize_target_view(view: TargetView, max_size: int) -> TargetView:
    old = view.size
    new = resized_shape(*old, max_size)
    if new == old:
        return view
    sx, sy = _scales(old, new)
    masks = resize_masks(view.masks, new)
    present = view.present & masks.flatten(1).any(dim=1)  # a sliver can vanish when downsampled
    return replace(view, K=scale_intrinsics(view.K.double(), sx, sy).float(), masks=masks, present=present)
