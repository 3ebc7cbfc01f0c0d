"""Initialise a :class:`~usl.model.detector.MaskRCNN` from a torchvision or detectron2 checkpoint.

Every file key must be known to its layout's table (:mod:`.layouts`), every target must exist
with the same shape, and every part of the detector the file touches (ResNet, FPN, RPN, box head,
box predictor, mask head) must be covered completely; anything else is a :class:`WeightsError`
naming the key. Class-specific layers that do not fit the dataset's categories keep their fresh
initialisation and are reported. Parts the file does not touch at all (an ImageNet ResNet has no
FPN) keep theirs too.

Pixel convention: usl feeds RGB images in [0, 1] normalised by the ImageNet mean and std.
detectron2's MSRA weights expect BGR, 0-255, minus ``[103.53, 116.28, 123.675]`` (std 1), and that
mean is exactly 255 x the ImageNet mean, so ``x_bgr255 - mean = 255 * std * x_usl`` channel-reversed:
scaling conv1's input channels by ``255 * std`` and reversing them gives the identical network,
including at zero-padded borders. Checkpoints written afterwards are plain usl weights.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

import torch
from torch import nn

from ..backbone import IMAGENET_STD
from .files import WeightsError, WeightsFile, read_weights, resolve_format
from .layouts import CLASS_SPECIFIC, CONV1, LAYOUTS, Layout

Tensor = torch.Tensor
# Parts of the detector a file covers all or nothing of (first matching prefix wins).
PARTS = (
    "backbone.bottom_up.fc",
    "backbone.bottom_up",
    "backbone.fpn",
    "proposal_generator",
    "roi_heads.box_head",
    "roi_heads.box_predictor",
    "roi_heads.mask_head",
)
_SHOWN = 6


@dataclass
class InitReport:
    path: Path
    layout: str
    loaded: list[str] = field(default_factory=list)  # model keys
    reinitialised: list[str] = field(default_factory=list)  # model keys, with why
    unused: list[str] = field(default_factory=list)  # file keys
    kept: dict[str, int] = field(default_factory=dict)  # part -> model tensors left at their init
    folded_pixels: bool = False

    def lines(self) -> list[str]:
        lines = [
            f"init_weights {self.path} ({self.layout}): loaded {len(self.loaded)} tensors, "
            f"re-initialised {len(self.reinitialised)}, unused {len(self.unused)}"
        ]
        lines += [f"  re-initialised {entry}" for entry in self.reinitialised]
        if self.unused:
            lines.append(f"  unused: {_sample(self.unused)}")
        if self.kept:
            lines.append(
                "  not in the file (initialised as usual): " + ", ".join(f"{p} ({n})" for p, n in self.kept.items())
            )
        if self.folded_pixels:
            lines.append("  BGR 0-255 input convention folded into backbone.bottom_up.conv1 (usl feeds normalised RGB)")
        return lines


def init_detector(detector: nn.Module, path: str | Path | WeightsFile, fmt: str = "auto") -> InitReport:
    """Copy a pretrained checkpoint into ``detector`` (in place) and say what went where.

    ``path`` may be a file already read with :func:`read_weights` (then ``fmt`` is its own).
    """
    weights = path if isinstance(path, WeightsFile) else read_weights(path, fmt)
    layout = _detect_layout(weights)
    _check_resnet_variant(detector, layout, weights.path)
    model = detector.state_dict()
    report = InitReport(weights.path, layout.name)
    mapped = _map_keys(weights, layout, model, report)
    if layout.affine_norms:
        _fill_norm_statistics(detector, mapped)
    if layout.caffe2_pixels and CONV1 in mapped:
        mapped[CONV1] = (mapped[CONV1][0], _fold_caffe2_pixels(mapped[CONV1][1]))
        report.folded_pixels = True
    for target, (key, tensor) in list(mapped.items()):
        if tensor.shape == model[target].shape:
            continue
        if target not in CLASS_SPECIFIC:
            raise WeightsError(
                f"weights file {weights.path}: {key!r} has shape {tuple(tensor.shape)} but {target!r} "
                f"is {tuple(model[target].shape)} in this model (check the backbone/head config)"
            )
        report.reinitialised.append(
            f"{target}: file {tuple(weights.tensors[key].shape)} vs model {tuple(model[target].shape)} (categories differ)"
        )
        del mapped[target]
    _check_parts_complete(weights, mapped, model, report)
    with torch.no_grad():
        for target, (_, tensor) in mapped.items():
            model[target].copy_(tensor)
    report.loaded = sorted(mapped)
    return report


def trained_stride_in_1x1(path: str | Path, fmt: str = "auto") -> bool:
    """The bottleneck variant weights of this format were trained with (decided without reading the file)."""
    (stride,) = {layout.stride_in_1x1 for layout in LAYOUTS[resolve_format(path, fmt)]}
    return stride


def print_report(report: InitReport, stream: TextIO | None = None) -> None:
    """Print (to stderr by default) on the main process only: every rank loads the same file."""
    if torch.distributed.is_available() and torch.distributed.is_initialized() and torch.distributed.get_rank():
        return
    print("\n".join(report.lines()), file=stream or sys.stderr, flush=True)


def _detect_layout(weights: WeightsFile) -> Layout:
    for layout in LAYOUTS[weights.format]:
        if layout.signature in weights.tensors:
            return layout
    names = " or ".join(layout.name for layout in LAYOUTS[weights.format])
    raise WeightsError(
        f"weights file {weights.path} ({weights.format} format) is neither a {names}: "
        f"none of their signature keys is present (first keys: {_sample(sorted(weights.tensors))})"
    )


def _check_resnet_variant(detector: nn.Module, layout: Layout, path: Path) -> None:
    resnet = getattr(getattr(detector, "backbone", None), "bottom_up", None)
    if resnet is None or not hasattr(resnet, "stride_in_1x1"):
        raise WeightsError(f"weights file {path}: init_weights needs a ResNet backbone (resnet or resnet_fpn)")
    if resnet.depth >= 50 and resnet.stride_in_1x1 != layout.stride_in_1x1:
        where = "first 1x1 conv (MSRA ResNet)" if layout.stride_in_1x1 else "3x3 conv (ResNet v1.5)"
        raise WeightsError(
            f"weights file {path} ({layout.name}) was trained with the bottleneck stride on the {where}; "
            f"set model.detector.backbone.resnet.stride_in_1x1={str(layout.stride_in_1x1).lower()} or leave it unset"
        )


def _map_keys(
    weights: WeightsFile, layout: Layout, model: dict[str, Tensor], report: InitReport
) -> dict[str, tuple[str, Tensor]]:
    """``model key -> (file key, tensor in our layout)``; unknown keys and missing targets are errors."""
    has_mask_head = any(k.startswith("roi_heads.mask_head.") for k in model)
    mapped: dict[str, tuple[str, Tensor]] = {}
    for key, tensor in weights.tensors.items():
        known, target = layout.target(key)
        if not known:
            raise WeightsError(f"weights file {weights.path}: key {key!r} maps to nothing in the {layout.name} table")
        if target is None or (target.startswith("roi_heads.mask_head.") and not has_mask_head):
            report.unused.append(key)
            continue
        if target not in model:
            raise WeightsError(
                f"weights file {weights.path}: {key!r} maps to {target!r}, which this model does not have "
                "(an FPN checkpoint on the plain resnet backbone, a deeper ResNet, or another head than model.detector describes?)"
            )
        if target in mapped:
            raise WeightsError(f"weights file {weights.path}: {key!r} and {mapped[target][0]!r} both map to {target!r}")
        if layout.convert_class_layer is not None and target in CLASS_SPECIFIC:
            tensor = layout.convert_class_layer(target, tensor)
        mapped[target] = (key, tensor)
    return mapped


def _fill_norm_statistics(detector: nn.Module, mapped: dict[str, tuple[str, Tensor]]) -> None:
    """Affine-only norms: mean 0 and variance ``1 - eps``, so the norm applies exactly ``x * s + b``."""
    for target in [t for t in mapped if t.endswith(".weight")]:
        prefix = target[: -len("weight")]
        norm = detector.get_submodule(prefix[:-1])
        if not hasattr(norm, "running_var") or prefix + "running_var" in mapped:
            continue
        key = mapped[target][0]
        channels = mapped[target][1].shape[0]
        mapped[prefix + "running_mean"] = (key, torch.zeros(channels))
        mapped[prefix + "running_var"] = (key, torch.full((channels,), 1.0 - norm.eps))


def _fold_caffe2_pixels(weight: Tensor) -> Tensor:
    """conv1 for usl's normalised RGB input from one trained on BGR 0-255 minus the ImageNet mean."""
    scale = 255.0 * torch.tensor(IMAGENET_STD, dtype=torch.float64)
    return (weight.double().flip(1) * scale[None, :, None, None]).to(weight.dtype)


def _part(key: str) -> str:
    return next((p for p in PARTS if key.startswith(p + ".")), key.split(".")[0])


def _check_parts_complete(
    weights: WeightsFile, mapped: dict[str, tuple[str, Tensor]], model: dict[str, Tensor], report: InitReport
) -> None:
    """A part the file touches must be covered completely; untouched parts are only reported."""
    reinitialised = {entry.split(":")[0] for entry in report.reinitialised}
    covered = {_part(t) for t in mapped} | {_part(t) for t in reinitialised}
    missing = [
        k
        for k in model
        if _part(k) in covered and k not in mapped and k not in reinitialised and not k.endswith("num_batches_tracked")
    ]
    if missing:
        raise WeightsError(
            f"weights file {weights.path} lacks {len(missing)} tensor(s) of parts it provides: {_sample(missing)}"
        )
    for key in model:
        part = _part(key)
        if part not in covered and not key.endswith("num_batches_tracked"):
            report.kept[part] = report.kept.get(part, 0) + 1


def _sample(keys: list[str]) -> str:
    more = f" ... (+{len(keys) - _SHOWN})" if len(keys) > _SHOWN else ""
    return ", ".join(keys[:_SHOWN]) + more
