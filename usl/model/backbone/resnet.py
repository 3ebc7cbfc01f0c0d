"""ResNet-18/34/50/101 with torchvision's module and parameter names.

Same names mean a torchvision ``resnet50-*.pth`` state dict maps one to one (see
:mod:`usl.model.pretrained`). ``base_channels`` scales every stage's width (64 for
the real networks; e.g. 16 for a tiny CPU test network); names do not change.
"""

from __future__ import annotations

import torch
from torch import nn

from .norm import freeze_batch_norms, make_norm

Tensor = torch.Tensor

# ImageNet statistics for RGB images scaled to [0, 1], the input torchvision weights expect.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def conv3x3(in_channels: int, out_channels: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(in_channels, out_channels, kernel_size=3, stride=stride, padding=1, bias=False)


def conv1x1(in_channels: int, out_channels: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(in_channels, out_channels, kernel_size=1, stride=stride, bias=False)


class BasicBlock(nn.Module):
    expansion = 1

    def __init__(
        self,
        inplanes: int,
        planes: int,
        stride: int,
        downsample: nn.Module | None,
        norm: str,
        stride_in_1x1: bool = False,
    ):
        super().__init__()  # stride_in_1x1 only matters for bottlenecks; a basic block has no 1x1 conv
        self.conv1 = conv3x3(inplanes, planes, stride)
        self.bn1 = make_norm(norm, planes)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = conv3x3(planes, planes)
        self.bn2 = make_norm(norm, planes)
        self.downsample = downsample

    def forward(self, x: Tensor) -> Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + identity)


class Bottleneck(nn.Module):
    """ResNet bottleneck. v1.5 (torchvision) puts the stride on the 3x3 conv; the original
    MSRA ResNet (detectron2's ``STRIDE_IN_1X1``, its ImageNet and COCO weights) on the first 1x1."""

    expansion = 4

    def __init__(
        self,
        inplanes: int,
        planes: int,
        stride: int,
        downsample: nn.Module | None,
        norm: str,
        stride_in_1x1: bool = False,
    ):
        super().__init__()
        stride_1x1, stride_3x3 = (stride, 1) if stride_in_1x1 else (1, stride)
        self.conv1 = conv1x1(inplanes, planes, stride_1x1)
        self.bn1 = make_norm(norm, planes)
        self.conv2 = conv3x3(planes, planes, stride_3x3)
        self.bn2 = make_norm(norm, planes)
        self.conv3 = conv1x1(planes, planes * self.expansion)
        self.bn3 = make_norm(norm, planes * self.expansion)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x: Tensor) -> Tensor:
        identity = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        return self.relu(out + identity)


Block = type[BasicBlock | Bottleneck]
ARCHITECTURES: dict[int, tuple[Block, tuple[int, int, int, int]]] = {
    18: (BasicBlock, (2, 2, 2, 2)),
    34: (BasicBlock, (3, 4, 6, 3)),
    50: (Bottleneck, (3, 4, 6, 3)),
    101: (Bottleneck, (3, 4, 23, 3)),
}
STAGES = ("layer1", "layer2", "layer3", "layer4")
# Feature names handed to the FPN and their strides w.r.t. the input image.
STAGE_OUTPUTS = {"c2": 4, "c3": 8, "c4": 16, "c5": 32}


def channels_last_on(device: torch.device) -> bool:
    """Whether the feature maps are channels-last (NHWC) on ``device``: on the CPU (``ResNet.features``)."""
    return device.type == "cpu"


class ResNet(nn.Module):
    """torchvision-compatible ResNet; :meth:`features` gives the C2..C5 maps for detection.

    ``fc`` exists so classification checkpoints load strictly; detection never calls it.
    ``stride_in_1x1`` selects the original MSRA bottleneck (see :class:`Bottleneck`): same
    parameter shapes, different network, so it must match the weights' origin.
    """

    def __init__(
        self,
        depth: int = 50,
        base_channels: int = 64,
        norm: str = "BN",
        num_classes: int = 1000,
        stride_in_1x1: bool = False,
    ):
        super().__init__()
        if depth not in ARCHITECTURES:
            raise ValueError(f"unsupported ResNet depth {depth}; choose one of {sorted(ARCHITECTURES)}")
        block, layers = ARCHITECTURES[depth]
        self.depth = depth
        self.stride_in_1x1 = stride_in_1x1
        self.inplanes = base_channels
        self.conv1 = nn.Conv2d(3, base_channels, kernel_size=7, stride=2, padding=3, bias=False)
        self.bn1 = make_norm(norm, base_channels)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        self.stage_channels = {}
        for index, (stage, blocks) in enumerate(zip(STAGES, layers, strict=True)):
            planes = base_channels * 2**index
            setattr(self, stage, self._make_layer(block, planes, blocks, stride=1 if index == 0 else 2, norm=norm))
            self.stage_channels[f"c{index + 2}"] = planes * block.expansion
        self.avgpool = nn.AdaptiveAvgPool2d((1, 1))
        self.fc = nn.Linear(self.stage_channels["c5"], num_classes)
        self._init_weights()

    def _make_layer(self, block: Block, planes: int, blocks: int, stride: int, norm: str) -> nn.Sequential:
        downsample = None
        if stride != 1 or self.inplanes != planes * block.expansion:
            downsample = nn.Sequential(
                conv1x1(self.inplanes, planes * block.expansion, stride), make_norm(norm, planes * block.expansion)
            )
        layers = [block(self.inplanes, planes, stride, downsample, norm, self.stride_in_1x1)]
        self.inplanes = planes * block.expansion
        layers += [block(self.inplanes, planes, 1, None, norm, self.stride_in_1x1) for _ in range(1, blocks)]
        return nn.Sequential(*layers)

    def _init_weights(self) -> None:
        for module in self.modules():
            if isinstance(module, nn.Conv2d):
                nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(module, nn.BatchNorm2d):
                nn.init.ones_(module.weight)
                nn.init.zeros_(module.bias)

    def features(self, x: Tensor) -> dict[str, Tensor]:
        """C2..C5 feature maps (strides 4, 8, 16, 32).

        On the CPU the maps are channels-last (NHWC): oneDNN's convolutions, their backward and the
        stem's max-pool run faster in that layout (a ``tiny`` step's backbone ~15% less CPU), with
        the same values to float rounding. CUDA keeps NCHW: the layout was measured on the CPU only.
        The convolutions' weights follow with ``MaskRCNN.lay_out_weights_like_features``."""
        if channels_last_on(x.device):
            x = x.contiguous(memory_format=torch.channels_last)
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        outputs = {}
        for index, stage in enumerate(STAGES):
            x = getattr(self, stage)(x)
            outputs[f"c{index + 2}"] = x
        return outputs

    def forward(self, x: Tensor) -> Tensor:
        """Classification logits, as torchvision's ResNet."""
        return self.fc(torch.flatten(self.avgpool(self.features(x)["c5"]), 1))

    def freeze(self, freeze_at: int) -> None:
        """Freeze the stem (``freeze_at >= 1``) and the first ``freeze_at - 1`` stages.

        Frozen parts stop receiving gradients and their BatchNorms become frozen too,
        so their statistics no longer drift in train mode (detectron2's FREEZE_AT).
        """
        if not 0 <= freeze_at <= 1 + len(STAGES):
            raise ValueError(f"freeze_at must be in [0, {1 + len(STAGES)}], got {freeze_at}")
        if freeze_at == 0:
            return
        for name in ("conv1", "bn1") + STAGES[: freeze_at - 1]:
            frozen = freeze_batch_norms(getattr(self, name))
            frozen.requires_grad_(False)
            setattr(self, name, frozen)
