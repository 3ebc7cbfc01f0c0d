"""Layout head (paper Sec. 3.2): per-object depth z and depth extent rho from RoI features."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from usl.config import LayoutHeadConfig, LayoutRange

Tensor = torch.Tensor


@dataclass
class LayoutPrediction:
    z: Tensor  # (N,) depth of the object centre, metres, in [z0, z1]
    rho: Tensor  # (N,) depth extent, metres, in [rho0, rho1]


class LayoutHead(nn.Module):
    """RoIAlign features -> average pool -> ``num_fc`` x Linear+ReLU -> category-specific sigmoids.

    ``z = z0 + sigmoid(.) (z1 - z0)`` and ``rho = rho0 + sigmoid(.) (rho1 - rho0)``; like the box
    head's regressors, one output per category, picked by the object's label, so the head can
    learn per-category priors. The predictors start at zero: every object begins mid-range.
    """

    def __init__(self, in_channels: int, num_classes: int, cfg: LayoutHeadConfig, layout_range: LayoutRange):
        super().__init__()
        if not (layout_range.z1 > layout_range.z0 > 0 and layout_range.rho1 > layout_range.rho0 > 0):
            raise ValueError(f"layout range must satisfy z1 > z0 > 0 and rho1 > rho0 > 0, got {layout_range}")
        layers: list[nn.Module] = []
        width = in_channels
        for _ in range(cfg.num_fc):
            layers += [nn.Linear(width, cfg.fc_dim), nn.ReLU(inplace=True)]
            width = cfg.fc_dim
        self.mlp = nn.Sequential(*layers)
        self.z_pred = nn.Linear(width, num_classes)
        self.rho_pred = nn.Linear(width, num_classes)
        for layer in (self.z_pred, self.rho_pred):
            nn.init.normal_(layer.weight, std=0.001)
            nn.init.zeros_(layer.bias)
        self.layout_range = layout_range

    def forward(self, roi_features: Tensor, labels: Tensor) -> LayoutPrediction:
        """roi_features (N, C, P, P) pooled per object; labels (N,) contiguous category indices."""
        x = self.mlp(roi_features.mean(dim=(2, 3)))
        rows = torch.arange(len(labels), device=labels.device)
        z_unit = torch.sigmoid(self.z_pred(x)[rows, labels].float())
        rho_unit = torch.sigmoid(self.rho_pred(x)[rows, labels].float())
        z, rho = self.layout_range.from_unit(z_unit, rho_unit)
        return LayoutPrediction(z=z, rho=rho)
