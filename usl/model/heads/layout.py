"""Layout head (paper Sec. 3.2): per-object depth z and depth extent rho from RoI features
(and, as an option, from the 2D box's camera rays)."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from usl.geometry.cameras import pixel_rays
from usl.model.config import LayoutHeadConfig, LayoutRange

Tensor = torch.Tensor

# Numbers box_geometry appends to the pooled features: (x, y) of the two corner rays, log width, log height.
BOX_GEOMETRY_DIM = 6
POOLER_RESOLUTION = 7  # RoIAlign bins per side (detectron2's box pooler), then averaged to one 1 x C vector


def box_geometry(boxes: Tensor, K: Tensor) -> Tensor:
    """(N, 6) camera-frame description of xyxy ``boxes`` (N, 4) seen through ``K`` (N, 3, 3).

    The corners become rays ``K^-1 [u, v, 1]`` at unit homogeneous depth, so the numbers do not
    depend on the image's resolution or crop: with a per-category size prior, the box's angular
    size and its height in the image (where a floor-standing object meets the floor) say how far
    away the object is, which the RoI-pooled features, resampled to one grid, cannot.
    """
    rays = pixel_rays(boxes.view(-1, 2, 2), K)[..., :2]  # (N, corner, xy)
    size = (rays[:, 1] - rays[:, 0]).clamp_min(1e-6)
    return torch.cat([rays.reshape(-1, 4), size.log()], dim=1)


@dataclass
class LayoutPrediction:
    z: Tensor  # (N,) depth of the object centre, metres, in [z0, z1]
    rho: Tensor  # (N,) depth extent, metres, in [rho0, rho1]


class LayoutHead(nn.Module):
    """RoIAlign features -> average pool -> ``num_fc`` x Linear+ReLU -> category-specific sigmoids.

    ``z = z0 + sigmoid(.) (z1 - z0)`` and ``rho = rho0 + sigmoid(.) (rho1 - rho0)``; like the box
    head's regressors, one output per category, picked by the object's label, so the head can
    learn per-category priors. The predictors start at zero: every object begins mid-range.
    With ``cfg.box_geometry`` the MLP's input is the pooled features followed by :func:`box_geometry`.
    """

    def __init__(self, in_channels: int, num_classes: int, cfg: LayoutHeadConfig, layout_range: LayoutRange):
        super().__init__()
        if not (layout_range.z1 > layout_range.z0 > 0 and layout_range.rho1 > layout_range.rho0 > 0):
            raise ValueError(f"layout range must satisfy z1 > z0 > 0 and rho1 > rho0 > 0, got {layout_range}")
        layers: list[nn.Module] = []
        width = in_channels + (BOX_GEOMETRY_DIM if cfg.box_geometry else 0)
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
        self.box_geometry = cfg.box_geometry

    def forward(self, roi_features: Tensor, labels: Tensor, boxes: Tensor, K: Tensor) -> LayoutPrediction:
        """roi_features (N, C, P, P) pooled per object; labels (N,) contiguous category indices;
        boxes (N, 4) xyxy and K (N, 3, 3) the intrinsics of each object's image (used with
        ``box_geometry`` only)."""
        x = roi_features.mean(dim=(2, 3))
        if self.box_geometry:
            x = torch.cat([x, box_geometry(boxes.float(), K.float()).to(x.dtype)], dim=1)
        x = self.mlp(x)
        rows = torch.arange(len(labels), device=labels.device)
        z_unit = torch.sigmoid(self.z_pred(x)[rows, labels].float())
        rho_unit = torch.sigmoid(self.rho_pred(x)[rows, labels].float())
        z, rho = self.layout_range.from_unit(z_unit, rho_unit)
        return LayoutPrediction(z=z, rho=rho)
