"""The true masks of P (object, view) pairs whose views may differ in size, as one structure.

Padded, as PyTorch3D batches meshes: one (P, H, W) bool stack, each mask in its top-left corner
and False beyond it, up to the largest view's H and W, with each mask's own image size beside it.
The padding adds no mask pixel and moves no box; whatever needs the image's extent (the dynamic
renderer's valid cells, the silhouette Chamfer's scale) reads ``sizes``, never the padded shape.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
import torch.nn.functional as F

from usl.utils.transfer import constant, to_device

Tensor = torch.Tensor


@dataclass(frozen=True)
class PaddedMasks:
    """Mask p is ``padded[p, :sizes[p, 0], :sizes[p, 1]]``; the rest of its plane is False."""

    padded: Tensor  # (P, H, W) bool, H and W the largest of the sizes
    sizes: Tensor  # (P, 2) int64 (height, width) of each mask's image

    def __post_init__(self) -> None:
        if self.padded.dtype != torch.bool or self.padded.dim() != 3 or self.sizes.shape != (len(self.padded), 2):
            raise ValueError(
                f"PaddedMasks: padded must be (P, H, W) bool and sizes (P, 2), "
                f"got {self.padded.dtype} {tuple(self.padded.shape)} and {tuple(self.sizes.shape)}"
            )

    def __len__(self) -> int:
        return self.padded.shape[0]

    @classmethod
    def of(cls, masks: Tensor | Sequence[Tensor]) -> PaddedMasks:
        """From (P, H, W) masks of one image size, or from P masks of their own (H_p, W_p) sizes."""
        if isinstance(masks, Tensor):
            sizes = constant(tuple(masks.shape[-2:]), torch.int64, masks.device).expand(len(masks), 2)
            return cls(masks.bool(), sizes)
        if not len(masks):
            return cls(torch.zeros(0, 1, 1, dtype=torch.bool), torch.zeros(0, 2, dtype=torch.int64))
        sizes = to_device([tuple(m.shape[-2:]) for m in masks], masks[0].device, torch.int64)
        return cls(pad_cat([m[None].bool() for m in masks]), sizes)


def pad_cat(blocks: Sequence[Tensor]) -> Tensor:
    """Blocks of (n_i, H_i, W_i) bool masks as one (sum n_i, H, W) stack, each smaller block padded with
    False to the largest H and W (an op per block, not per mask)."""
    height, width = max(b.shape[-2] for b in blocks), max(b.shape[-1] for b in blocks)
    return torch.cat(
        [
            b if b.shape[-2:] == (height, width) else F.pad(b, (0, width - b.shape[-1], 0, height - b.shape[-2]))
            for b in blocks
        ]
    )
