"""Backbone configuration, the ResNet-FPN backbone, and the registry-based builder."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import torch
from torch import nn

from .fpn import FPN
from .registry import BACKBONES
from .resnet import STAGE_OUTPUTS, ResNet

Tensor = torch.Tensor


@dataclass(frozen=True)
class ShapeSpec:
    """Channels and stride (w.r.t. the input image) of one feature map."""

    channels: int
    stride: int


@dataclass
class ResNetConfig:
    depth: int = 50
    base_channels: int = 64  # width of the stem; stages have 1x, 2x, 4x, 8x (x4 for bottlenecks)
    norm: str = "FrozenBN"  # "BN" or "FrozenBN"
    freeze_at: int = 2  # 0: train all; 1: freeze stem; k: also freeze the first k-1 stages
    # Bottleneck stride on the first 1x1 conv (original MSRA ResNet, detectron2 weights) instead of
    # the 3x3 (v1.5, torchvision). None: as the model's init weights need (ModelConfig resolves it).
    stride_in_1x1: Optional[bool] = None
    weights: Optional[str] = None  # deprecated: moved to model.init_weights (ModelConfig forwards it)


@dataclass
class FPNConfig:
    out_channels: int = 256
    add_p6: bool = True


@dataclass
class BackboneConfig:
    name: str = "resnet_fpn"
    resnet: ResNetConfig = field(default_factory=ResNetConfig)
    fpn: FPNConfig = field(default_factory=FPNConfig)

    @classmethod
    def tiny(cls) -> "BackboneConfig":
        """ResNet-18 at a quarter width with a 32-channel FPN: a few hundred K params, for CPU tests."""
        return cls(resnet=ResNetConfig(depth=18, base_channels=16, norm="BN", freeze_at=0), fpn=FPNConfig(32))


class ResNetFPN(nn.Module):
    """``bottom_up`` ResNet (torchvision names) + ``fpn``; ``forward(images) -> {"p2": ..., "p6": ...}``."""

    def __init__(self, bottom_up: ResNet, fpn: FPN):
        super().__init__()
        self.bottom_up = bottom_up
        self.fpn = fpn
        # Detection never uses the classifier; keep it (for strict loading) but out of training.
        self.bottom_up.fc.requires_grad_(False)

    def forward(self, images: Tensor) -> dict[str, Tensor]:
        return self.fpn(self.bottom_up.features(images))

    def output_shape(self) -> dict[str, ShapeSpec]:
        return {name: ShapeSpec(self.fpn.out_channels, stride) for name, stride in self.fpn.out_strides.items()}

    @property
    def size_divisibility(self) -> int:
        """Inputs padded to a multiple of the deepest ResNet stride keep C2..C5 exactly aligned.

        (P6, a stride-2 max-pool of P5, simply rounds up.)
        """
        return max(STAGE_OUTPUTS.values())


@BACKBONES.register("resnet_fpn")
def build_resnet_fpn(cfg: BackboneConfig) -> ResNetFPN:
    if cfg.resnet.weights:
        raise ValueError(
            f"backbone.resnet.weights={cfg.resnet.weights!r} no longer loads here: initialise the whole model "
            "with model.init_weights (usl.model.pretrained.init_detector)"
        )
    resnet = ResNet(
        cfg.resnet.depth, cfg.resnet.base_channels, cfg.resnet.norm, stride_in_1x1=bool(cfg.resnet.stride_in_1x1)
    )
    resnet.freeze(cfg.resnet.freeze_at)
    fpn = FPN(resnet.stage_channels, STAGE_OUTPUTS, cfg.fpn.out_channels, cfg.fpn.add_p6)
    return ResNetFPN(resnet, fpn)


def build_backbone(cfg: BackboneConfig) -> nn.Module:
    """Build the backbone registered under ``cfg.name``; it must offer ``output_shape()``."""
    return BACKBONES.get(cfg.name)(cfg)
