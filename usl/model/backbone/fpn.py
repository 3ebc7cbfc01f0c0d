"""Feature Pyramid Network (Lin et al. 2017) over named bottom-up feature maps."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import torch
import torch.nn.functional as F
from torch import nn

Tensor = torch.Tensor


class FPN(nn.Module):
    """Top-down pathway with lateral 1x1 and output 3x3 convs, plus P6.

    Input ``c{k}`` maps (stride ``2**k``) become ``p{k}`` maps with ``out_channels``
    channels; ``P6`` is a stride-2 subsampling of P5 (max-pool, kernel 1), used only
    by the RPN for the largest anchors, as in Mask R-CNN with FPN.
    """

    def __init__(
        self,
        in_channels: Mapping[str, int],
        in_strides: Mapping[str, int],
        out_channels: int = 256,
    ):
        super().__init__()
        self.in_features = list(in_channels)
        levels = [int(math.log2(in_strides[name])) for name in self.in_features]
        if levels != list(range(levels[0], levels[0] + len(levels))):
            raise ValueError(f"FPN inputs must have consecutive power-of-two strides, got {dict(in_strides)}")
        self.lateral_convs = nn.ModuleList(nn.Conv2d(in_channels[n], out_channels, 1) for n in self.in_features)
        self.output_convs = nn.ModuleList(nn.Conv2d(out_channels, out_channels, 3, padding=1) for _ in self.in_features)
        out_levels = [*levels, levels[-1] + 1]
        self.out_strides = {f"p{level}": 2**level for level in out_levels}
        self.out_channels = out_channels
        for conv in [*self.lateral_convs, *self.output_convs]:
            nn.init.kaiming_uniform_(conv.weight, a=1)  # "c2_xavier_fill", the FPN paper's init
            nn.init.zeros_(conv.bias)

    def forward(self, bottom_up: Mapping[str, Tensor]) -> dict[str, Tensor]:
        """``{"p2": ..., "p6": ...}``, finest level first."""
        inputs: Sequence[Tensor] = [bottom_up[name] for name in self.in_features]
        names = list(self.out_strides)
        top_down = self.lateral_convs[-1](inputs[-1])
        results = [self.output_convs[-1](top_down)]
        for index in range(len(inputs) - 2, -1, -1):
            lateral = self.lateral_convs[index](inputs[index])
            # Upsample to the lateral's size (not by 2) so odd input sizes also work.
            top_down = lateral + F.interpolate(top_down, size=lateral.shape[-2:], mode="nearest")
            results.insert(0, self.output_convs[index](top_down))
        results.append(F.max_pool2d(results[-1], kernel_size=1, stride=2))
        return dict(zip(names, results, strict=True))
