"""Backbone configuration, the plain ResNet and ResNet-FPN backbones, and the registry-based builder."""

from __future__ import annotations

from dataclasses import dataclass, field

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
    depth: int = 50  # 18, 34 (basic blocks), 50, 101 (bottlenecks): as the init weights were trained
    base_channels: int = 64  # width of the stem; stages have 1x, 2x, 4x, 8x (x4 for bottlenecks); smaller: faster
    norm: str = "FrozenBN"  # "BN" (batch statistics: from scratch) | "FrozenBN" (pretrained, small batches)
    freeze_at: int = 2  # 0: train all; 1: freeze stem; k: also the first k-1 stages (keeps pretrained ones, faster)
    # Bottleneck stride on the first 1x1 conv (original MSRA ResNet, detectron2 weights) instead of
    # the 3x3 (v1.5, torchvision). None: as the model's init weights need (ModelConfig resolves it).
    stride_in_1x1: bool | None = None


@dataclass
class FPNConfig:
    out_channels: int = 256  # channels of every FPN level (p2..p6, p6 a stride-2 max-pool of p5); fewer: faster


@dataclass
class BackboneConfig:
    name: str = "resnet_fpn"  # key in BACKBONES: "resnet_fpn" (p2..p6, the paper's) | "resnet" (res2..res5: Mesh R-CNN)
    resnet: ResNetConfig = field(default_factory=ResNetConfig)
    fpn: FPNConfig = field(default_factory=FPNConfig)

    @classmethod
    def tiny(cls) -> BackboneConfig:
        """ResNet-18 at a quarter width with a 32-channel FPN: a few hundred K params, for CPU tests."""
        return cls(resnet=ResNetConfig(depth=18, base_channels=16, norm="BN", freeze_at=0), fpn=FPNConfig(32))


class ResNetBackbone(nn.Module):
    """A plain ``bottom_up`` ResNet (torchvision names): ``forward(images) -> {"res2": ..., "res5": ...}``.

    The stage outputs conv2_3 .. conv5_3 of a ResNet-50 (strides 4 .. 32, 256 .. 2048 channels), as
    Mesh R-CNN's ShapeNet model samples them; detectron2 names them res2 .. res5.
    """

    def __init__(self, bottom_up: ResNet):
        super().__init__()
        self.bottom_up = bottom_up
        self.bottom_up.fc.requires_grad_(False)  # kept for strict loading, never used

    def forward(self, images: Tensor) -> dict[str, Tensor]:
        return {_plain_name(name): x for name, x in self.bottom_up.features(images).items()}

    def output_shape(self) -> dict[str, ShapeSpec]:
        channels = self.bottom_up.stage_channels
        return {_plain_name(name): ShapeSpec(channels[name], stride) for name, stride in STAGE_OUTPUTS.items()}

    @property
    def size_divisibility(self) -> int:
        """Inputs padded to a multiple of the deepest stride keep res2..res5 exactly aligned."""
        return max(STAGE_OUTPUTS.values())


class ResNetFPN(ResNetBackbone):
    """``bottom_up`` ResNet (torchvision names) + ``fpn``; ``forward(images) -> {"p2": ..., "p6": ...}``.

    ``size_divisibility`` is the plain ResNet's (P6, a stride-2 max-pool of P5, simply rounds up).
    """

    def __init__(self, bottom_up: ResNet, fpn: FPN):
        super().__init__(bottom_up)
        self.fpn = fpn

    def forward(self, images: Tensor) -> dict[str, Tensor]:
        return self.fpn(self.bottom_up.features(images))

    def output_shape(self) -> dict[str, ShapeSpec]:
        return {name: ShapeSpec(self.fpn.out_channels, stride) for name, stride in self.fpn.out_strides.items()}


def _plain_name(stage: str) -> str:
    """``c2`` (the ResNet's and the FPN's input name) -> ``res2`` (a plain backbone's output)."""
    return "res" + stage[1:]


def _build_resnet(cfg: BackboneConfig) -> ResNet:
    resnet = ResNet(
        cfg.resnet.depth, cfg.resnet.base_channels, cfg.resnet.norm, stride_in_1x1=bool(cfg.resnet.stride_in_1x1)
    )
    resnet.freeze(cfg.resnet.freeze_at)
    return resnet


@BACKBONES.register("resnet")
def build_resnet(cfg: BackboneConfig) -> ResNetBackbone:
    """The plain ResNet: every stage output, no FPN (``cfg.fpn`` is unused)."""
    return ResNetBackbone(_build_resnet(cfg))


@BACKBONES.register("resnet_fpn")
def build_resnet_fpn(cfg: BackboneConfig) -> ResNetFPN:
    resnet = _build_resnet(cfg)
    fpn = FPN(resnet.stage_channels, STAGE_OUTPUTS, cfg.fpn.out_channels)
    return ResNetFPN(resnet, fpn)


def build_backbone(cfg: BackboneConfig) -> nn.Module:
    """Build the backbone registered under ``cfg.name``; it must offer ``output_shape()``."""
    return BACKBONES.get(cfg.name)(cfg)
