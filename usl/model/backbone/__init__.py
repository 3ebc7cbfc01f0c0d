"""Backbones: torchvision-compatible ResNets and a Feature Pyramid Network."""

from .build import (
    BackboneConfig,
    FPNConfig,
    ResNetBackbone,
    ResNetConfig,
    ResNetFPN,
    ShapeSpec,
    build_backbone,
    build_resnet,
    build_resnet_fpn,
)
from .fpn import FPN
from .norm import FrozenBatchNorm2d, freeze_batch_norms
from .registry import BACKBONES, Registry
from .resnet import IMAGENET_MEAN, IMAGENET_STD, ResNet

__all__ = [
    "BACKBONES",
    "BackboneConfig",
    "FPN",
    "FPNConfig",
    "FrozenBatchNorm2d",
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "Registry",
    "ResNet",
    "ResNetBackbone",
    "ResNetConfig",
    "ResNetFPN",
    "ShapeSpec",
    "build_backbone",
    "build_resnet",
    "build_resnet_fpn",
    "freeze_batch_norms",
]
