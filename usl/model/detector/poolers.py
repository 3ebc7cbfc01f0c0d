"""RoIAlign over an FPN: each box is pooled from the level that matches its size."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import torch
from torch import nn

from ..ops import box_area, convert_boxes_to_rois, roi_align_levels

Tensor = torch.Tensor


def assign_boxes_to_levels(
    boxes: Tensor, min_level: int, max_level: int, canonical_box_size: float, canonical_level: int
) -> Tensor:
    """FPN paper eq. 1: ``k = floor(k0 + log2(sqrt(area) / 224))``, clamped to the pyramid.

    Returns, per box, the index into the pooled levels (0 = ``min_level``).
    """
    size = torch.sqrt(box_area(boxes).clamp(min=0))
    level = torch.floor(canonical_level + torch.log2(size / canonical_box_size + 1e-8))
    return (level.clamp(min=min_level, max=max_level) - min_level).long()


class MultiScaleRoIAlign(nn.Module):
    """Pool ``(R, C, out, out)`` features for boxes given per image, from named FPN levels.

    ``forward(features, boxes)`` takes the backbone's feature dict (it picks its own
    ``in_features``) and ``list[Tensor[Ri, 4]]`` boxes in input-image pixels; rows of the
    result follow the boxes, image by image. Uses aligned RoIAlign (ROIAlignV2).
    """

    def __init__(
        self,
        in_features: Sequence[str],
        strides: Sequence[int],
        output_size: int,
        sampling_ratio: int = 0,
        canonical_box_size: float = 224.0,
        canonical_level: int = 4,
    ):
        super().__init__()
        levels = [int(round(math.log2(s))) for s in strides]
        if levels != list(range(levels[0], levels[0] + len(levels))):
            raise ValueError(f"pooled levels must have consecutive power-of-two strides, got {list(strides)}")
        self.in_features = list(in_features)
        self.scales = [1.0 / s for s in strides]
        self.min_level, self.max_level = levels[0], levels[-1]
        self.output_size = output_size
        self.sampling_ratio = sampling_ratio
        self.canonical_box_size = canonical_box_size
        self.canonical_level = canonical_level

    def forward(self, features: Mapping[str, Tensor], boxes: Sequence[Tensor]) -> Tensor:
        maps = [features[name] for name in self.in_features]
        rois = convert_boxes_to_rois(boxes, maps[0])
        level_of = assign_boxes_to_levels(
            rois[:, 1:], self.min_level, self.max_level, self.canonical_box_size, self.canonical_level
        )
        # all levels in one pass: no per-level nonzero, one host read of the RoI sizes
        return roi_align_levels(maps, self.scales, rois, level_of, self.output_size, self.sampling_ratio, aligned=True)
