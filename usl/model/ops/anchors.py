"""Anchor boxes for every location of every feature level.

Layout (detectron2's): per level, anchors are ordered location-major, i.e. index
``(y * W + x) * A + a`` where ``a`` runs over (size, aspect ratio) pairs, sizes outer.
The RPN head flattens its predictions in the same order.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import nn

Tensor = torch.Tensor


def cell_anchors(sizes: Sequence[float], aspect_ratios: Sequence[float]) -> Tensor:
    """Anchors centred on (0, 0), one per (size, aspect ratio): ``(A, 4)``.

    ``size`` is the square root of the area and ``aspect_ratio`` is height / width.
    """
    anchors = []
    for size in sizes:
        area = float(size) ** 2
        for ratio in aspect_ratios:
            w = math.sqrt(area / ratio)
            h = ratio * w
            anchors.append([-w / 2.0, -h / 2.0, w / 2.0, h / 2.0])
    return torch.tensor(anchors, dtype=torch.float32)


# feature-size layouts whose anchors are kept (evaluation at several image sizes)
_CACHED_GRIDS = 8


class AnchorGenerator(nn.Module):
    """One set of cell anchors per feature level, tiled at that level's stride.

    Args:
        sizes: per level, the anchor sizes (sqrt of area, in input pixels).
        aspect_ratios: height / width ratios, shared by all levels.
        strides: per level, the feature stride in input pixels.
        offset: where in a feature cell anchor centres sit, in units of the stride
            (0.0: at the cell's top-left corner, as detectron2's default; 0.5: the centre).
    """

    def __init__(
        self,
        sizes: Sequence[Sequence[float]],
        aspect_ratios: Sequence[float],
        strides: Sequence[int],
        offset: float = 0.0,
    ):
        super().__init__()
        if len(sizes) != len(strides):
            raise ValueError(f"need one size list per level: {len(sizes)} size lists for {len(strides)} strides")
        if not 0.0 <= offset < 1.0:
            raise ValueError(f"anchor offset must be in [0, 1), got {offset}")
        self.strides = [int(s) for s in strides]
        self.offset = offset
        for level, level_sizes in enumerate(sizes):
            self.register_buffer(f"cell_anchors_{level}", cell_anchors(level_sizes, aspect_ratios), persistent=False)
        # the grids of the last few feature sizes: a training run sees one or a few, so a step builds none
        self._grids: dict[tuple, list[Tensor]] = {}

    @property
    def num_anchors_per_location(self) -> list[int]:
        return [self._cell(level).shape[0] for level in range(len(self.strides))]

    def _cell(self, level: int) -> Tensor:
        return getattr(self, f"cell_anchors_{level}")

    def forward(self, feature_sizes: Sequence[tuple[int, int]]) -> list[Tensor]:
        """Anchors ``(H * W * A, 4)`` for each level's ``(H, W)`` feature grid (cached: do not modify them)."""
        if len(feature_sizes) != len(self.strides):
            raise ValueError(f"expected {len(self.strides)} feature levels, got {len(feature_sizes)}")
        cell = self._cell(0)
        key = (tuple((int(h), int(w)) for h, w in feature_sizes), cell.device, cell.dtype)
        if key not in self._grids:
            if len(self._grids) >= _CACHED_GRIDS:
                self._grids.clear()
            self._grids[key] = self._build(feature_sizes)
        return list(self._grids[key])

    def _build(self, feature_sizes: Sequence[tuple[int, int]]) -> list[Tensor]:
        anchors = []
        for level, ((height, width), stride) in enumerate(zip(feature_sizes, self.strides, strict=True)):
            cell = self._cell(level)
            xs = (torch.arange(width, device=cell.device, dtype=cell.dtype) + self.offset) * stride
            ys = (torch.arange(height, device=cell.device, dtype=cell.dtype) + self.offset) * stride
            shift_y, shift_x = torch.meshgrid(ys, xs, indexing="ij")
            shifts = torch.stack([shift_x, shift_y, shift_x, shift_y], dim=-1).reshape(-1, 1, 4)
            anchors.append((shifts + cell[None]).reshape(-1, 4))
        return anchors
