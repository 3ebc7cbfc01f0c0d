"""Axis-aligned box maths on ``(N, 4)`` tensors in ``[x0, y0, x1, y1]`` form.

Boxes live in the continuous pixel frame of docs/design.md §2 (the image spans
``[0, W] x [0, H]``), so areas and IoUs are computed without the legacy "+1".
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from usl.utils.transfer import to_device

Tensor = torch.Tensor

# Largest log-scale step a predicted delta may take: a box may grow at most
# 1000/16 times in one decode, which keeps exp() finite for wild early predictions.
DEFAULT_SCALE_CLAMP = math.log(1000.0 / 16)


def box_area(boxes: Tensor) -> Tensor:
    """Area of each box, ``(..., 4) -> (...)``; inverted boxes give negative areas."""
    size = boxes[..., 2:] - boxes[..., :2]
    return size[..., 0] * size[..., 1]


def pairwise_intersection(boxes1: Tensor, boxes2: Tensor) -> Tensor:
    """Intersection areas, ``(..., N, 4), (..., M, 4) -> (..., N, M)`` (leading dims broadcast)."""
    top_left = torch.maximum(boxes1[..., :, None, :2], boxes2[..., None, :, :2])
    bottom_right = torch.minimum(boxes1[..., :, None, 2:], boxes2[..., None, :, 2:])
    wh = (bottom_right - top_left).clamp(min=0)
    return wh[..., 0] * wh[..., 1]


def box_iou(boxes1: Tensor, boxes2: Tensor) -> Tensor:
    """Pairwise intersection over union, ``(..., N, 4), (..., M, 4) -> (..., N, M)``, e.g. every
    image's ground truth against its predictions at once (leading dims broadcast).

    Pairs whose union is empty (two degenerate boxes) give NaN, as in torchvision,
    so that they never pass an ``iou > threshold`` test.
    """
    inter = pairwise_intersection(boxes1, boxes2)
    union = box_area(boxes1)[..., :, None] + box_area(boxes2)[..., None, :] - inter
    return inter / union


def stack_padded(boxes: Sequence[Tensor]) -> tuple[Tensor, Tensor]:
    """Per-image ``(K_i, 4)`` boxes as one ``(N, max K_i, 4)`` tensor padded with zero boxes, and
    the ``(N, max K_i)`` mask of real rows: batched maths over images without a per-image loop."""
    longest = max((len(b) for b in boxes), default=0)
    padded = torch.stack([torch.nn.functional.pad(b, (0, 0, 0, longest - len(b))) for b in boxes])
    lengths = to_device([len(b) for b in boxes], padded.device)
    return padded, torch.arange(longest, device=padded.device) < lengths[:, None]


def padded_match_quality(gt_boxes: Sequence[Tensor], boxes: Tensor) -> tuple[Tensor, Tensor]:
    """Every image's ground truth against its ``boxes`` at once: the padded ground truth ``(N, G, 4)``
    and the IoUs ``(N, G, B)`` a ``Matcher`` reads, with -1 in the padded rows, below every
    threshold and never a best match, so each image matches as it would alone. ``boxes``: ``(N, B, 4)``,
    or ``(1, B, 4)`` shared by all images (anchors)."""
    padded, real = stack_padded(gt_boxes)
    return padded, torch.where(real[..., None], box_iou(padded, boxes), -1.0)


def clip_boxes(boxes: Tensor, image_size: tuple[int, int]) -> Tensor:
    """Clip ``(..., 4)`` boxes to an image of ``(height, width)``."""
    height, width = image_size
    x = boxes[..., 0::2].clamp(min=0, max=width)
    y = boxes[..., 1::2].clamp(min=0, max=height)
    return torch.stack([x[..., 0], y[..., 0], x[..., 1], y[..., 1]], dim=-1)


def nonempty_boxes(boxes: Tensor, min_size: float = 0.0) -> Tensor:
    """Bool mask of boxes whose width and height both exceed ``min_size``."""
    widths = boxes[:, 2] - boxes[:, 0]
    heights = boxes[:, 3] - boxes[:, 1]
    return (widths > min_size) & (heights > min_size)


class Box2BoxTransform:
    """Encode a target box relative to a reference box as ``(dx, dy, dw, dh)`` and back.

    The R-CNN parameterisation: centre offsets in units of the reference size, and
    log size ratios, each multiplied by ``weights`` (``(1, 1, 1, 1)`` for the RPN,
    ``(10, 10, 5, 5)`` for the box head, the detectron2/torchvision defaults).
    """

    def __init__(self, weights: Sequence[float], scale_clamp: float = DEFAULT_SCALE_CLAMP):
        if len(weights) != 4:
            raise ValueError(f"Box2BoxTransform needs 4 weights, got {tuple(weights)}")
        self.weights = tuple(float(w) for w in weights)
        self.scale_clamp = scale_clamp

    def get_deltas(self, src_boxes: Tensor, target_boxes: Tensor) -> Tensor:
        """Deltas that turn ``src_boxes`` into ``target_boxes``, both ``(N, 4)``."""
        src_w, src_h, src_cx, src_cy = _size_and_centre(src_boxes)
        tgt_w, tgt_h, tgt_cx, tgt_cy = _size_and_centre(target_boxes)
        wx, wy, ww, wh = self.weights
        return torch.stack(
            [
                wx * (tgt_cx - src_cx) / src_w,
                wy * (tgt_cy - src_cy) / src_h,
                ww * torch.log(tgt_w / src_w),
                wh * torch.log(tgt_h / src_h),
            ],
            dim=1,
        )

    def apply_deltas(self, deltas: Tensor, boxes: Tensor) -> Tensor:
        """Decode ``deltas`` of shape ``(N, 4k)`` against ``boxes`` ``(N, 4)`` -> ``(N, 4k)``.

        ``k > 1`` holds one box per class (class-specific regression). Computed in at
        least float32, since exp() of half-precision deltas loses whole pixels.
        """
        deltas = deltas.to(torch.promote_types(deltas.dtype, torch.float32))
        boxes = boxes.to(deltas.dtype)
        widths, heights, ctr_x, ctr_y = (t[:, None] for t in _size_and_centre(boxes))
        wx, wy, ww, wh = self.weights
        dx = deltas[:, 0::4] / wx
        dy = deltas[:, 1::4] / wy
        dw = (deltas[:, 2::4] / ww).clamp(max=self.scale_clamp)
        dh = (deltas[:, 3::4] / wh).clamp(max=self.scale_clamp)
        pred_cx = dx * widths + ctr_x
        pred_cy = dy * heights + ctr_y
        pred_w = torch.exp(dw) * widths
        pred_h = torch.exp(dh) * heights
        decoded = torch.stack(
            [pred_cx - 0.5 * pred_w, pred_cy - 0.5 * pred_h, pred_cx + 0.5 * pred_w, pred_cy + 0.5 * pred_h],
            dim=2,
        )
        return decoded.reshape(deltas.shape)


def _size_and_centre(boxes: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    size = boxes[:, 2:] - boxes[:, :2]
    centre = boxes[:, :2] + 0.5 * size
    return size[:, 0], size[:, 1], centre[:, 0], centre[:, 1]
