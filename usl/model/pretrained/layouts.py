"""Key tables from upstream checkpoint layouts to :class:`usl.model.detector.MaskRCNN` state-dict keys.

Each layout is a list of (regex, target) rules read off the upstream module definitions:

* torchvision ``maskrcnn_resnet50_fpn`` (``torchvision/models/detection``): ``backbone.body`` is a
  torchvision ResNet (our names), ``backbone.fpn.{inner,layer}_blocks.i[.0]`` the FPN, ``rpn.head``,
  ``roi_heads.box_head.fc6/fc7``, ``roi_heads.mask_head.mask_fcn1..4`` (or ``i.0`` since torchvision
  0.13), ``roi_heads.mask_predictor.{conv5_mask,mask_fcn_logits}``. Class layers include a background
  class at index 0 (scores, box deltas and masks).
* torchvision ImageNet ``resnet50``: our ResNet names exactly (plus ``fc``).
* detectron2 ``GeneralizedRCNN`` (``detectron2/modeling``): ``backbone.bottom_up.{stem,res2..res5}``
  with ``convK.norm`` and ``shortcut``, ``backbone.fpn_{lateral,output}{2..5}``,
  ``proposal_generator.rpn_head``, ``roi_heads.box_head.fc1/fc2``, ``roi_heads.mask_head``; PointRend
  (``projects/PointRend``) has ``roi_heads.mask_head.coarse_head.{reduce_spatial_dim_conv,fc1,fc2,prediction}``
  and ``roi_heads.mask_head.point_head.{fc1..3,predictor}`` instead of the conv mask head.
  Class layers already have our layout (background last in ``cls_score``, none in the others).
* Caffe2 / MSRA ``R-50.pkl`` (names as ``detectron2/checkpoint/c2_model_loading.py`` reads them):
  ``conv1_w``, ``res_conv1_bn_{s,b}``, ``res{2..5}_{i}_branch{1,2a,2b,2c}_{w,bn_s,bn_b}``, ``fc1000``.
  Its norms are affine only (statistics folded into scale and shift).

A target ``None`` marks a tensor we know and deliberately do not use.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass

import torch

Tensor = torch.Tensor
Target = str | Callable[[re.Match], str] | None

# Layers whose shape depends on the number of categories: re-initialised when they do not fit.
# PointRend's point head reads the coarse logits of every class in each layer, so its layers all count.
CLASS_SPECIFIC = frozenset(
    f"roi_heads.{layer}.{param}"
    for layer in (
        "box_predictor.cls_score",
        "box_predictor.bbox_pred",
        "mask_head.predictor",
        "mask_head.coarse_head.predictor",
        "mask_head.point_head.predictor",
        *(f"mask_head.point_head.fcs.{i}" for i in range(3)),
    )
    for param in ("weight", "bias")
)
CONV1 = "backbone.bottom_up.conv1.weight"


@dataclass(frozen=True)
class Rule:
    pattern: re.Pattern
    target: Target

    def apply(self, match: re.Match) -> str | None:
        if self.target is None or isinstance(self.target, str):
            return None if self.target is None else match.expand(self.target)
        return self.target(match)


def rules(*pairs: tuple[str, Target]) -> tuple[Rule, ...]:
    return tuple(Rule(re.compile(pattern + "$"), target) for pattern, target in pairs)


@dataclass(frozen=True)
class Layout:
    name: str
    signature: str  # a key every file of this layout has
    rules: tuple[Rule, ...]
    stride_in_1x1: bool  # the ResNet it was trained as (see usl.model.backbone.resnet.Bottleneck)
    caffe2_pixels: bool = False  # trained on BGR 0-255 mean-subtracted inputs (std 1)
    affine_norms: bool = False  # norms hold scale and shift only
    convert_class_layer: Callable[[str, Tensor], Tensor] | None = None

    def target(self, key: str) -> tuple[bool, str | None]:
        """``(known, model key or None)`` for a file key."""
        for rule in self.rules:
            match = rule.pattern.match(key)
            if match:
                return True, rule.apply(match)
        return False, None


def _stage(match: re.Match, group: int = 1) -> str:
    """detectron2/Caffe2 ``res2..res5`` are torchvision's ``layer1..layer4``."""
    return f"backbone.bottom_up.layer{int(match[group]) - 1}"


def _torchvision_class_layer(key: str, tensor: Tensor) -> Tensor:
    """torchvision keeps background at index 0 of every class layer: move or drop it."""
    if key.startswith("roi_heads.box_predictor.cls_score."):
        return torch.cat([tensor[1:], tensor[:1]])
    if key.startswith("roi_heads.box_predictor.bbox_pred."):
        return tensor[4:]
    return tensor[1:]  # mask predictor


_BATCH_COUNTER = (r".*\.num_batches_tracked", None)

TORCHVISION_MASK_RCNN = Layout(
    name="torchvision Mask R-CNN (maskrcnn_resnet50_fpn)",
    signature="backbone.body.conv1.weight",
    rules=rules(
        _BATCH_COUNTER,
        (r"backbone\.body\.(.+)", r"backbone.bottom_up.\1"),
        (r"backbone\.fpn\.inner_blocks\.(\d)\.(?:0\.)?(weight|bias)", r"backbone.fpn.lateral_convs.\1.\2"),
        (r"backbone\.fpn\.layer_blocks\.(\d)\.(?:0\.)?(weight|bias)", r"backbone.fpn.output_convs.\1.\2"),
        (r"rpn\.head\.conv\.(?:0\.0\.)?(weight|bias)", r"proposal_generator.head.conv.\1"),
        (r"rpn\.head\.cls_logits\.(weight|bias)", r"proposal_generator.head.objectness_logits.\1"),
        (r"rpn\.head\.bbox_pred\.(weight|bias)", r"proposal_generator.head.anchor_deltas.\1"),
        (r"roi_heads\.box_head\.fc6\.(weight|bias)", r"roi_heads.box_head.fcs.0.\1"),
        (r"roi_heads\.box_head\.fc7\.(weight|bias)", r"roi_heads.box_head.fcs.1.\1"),
        (r"roi_heads\.box_predictor\.(cls_score|bbox_pred)\.(weight|bias)", r"roi_heads.box_predictor.\1.\2"),
        (
            r"roi_heads\.mask_head\.mask_fcn(\d)\.(weight|bias)",
            lambda m: f"roi_heads.mask_head.convs.{int(m[1]) - 1}.{m[2]}",
        ),
        (r"roi_heads\.mask_head\.(\d)\.0\.(weight|bias)", r"roi_heads.mask_head.convs.\1.\2"),
        (r"roi_heads\.mask_predictor\.conv5_mask\.(weight|bias)", r"roi_heads.mask_head.deconv.\1"),
        (r"roi_heads\.mask_predictor\.mask_fcn_logits\.(weight|bias)", r"roi_heads.mask_head.predictor.\1"),
    ),
    stride_in_1x1=False,
    convert_class_layer=_torchvision_class_layer,
)

TORCHVISION_RESNET = Layout(
    name="torchvision ImageNet ResNet",
    signature="layer1.0.conv1.weight",
    rules=rules(_BATCH_COUNTER, (r"((?:conv1|bn1|layer[1-4]|fc)\..+)", r"backbone.bottom_up.\1")),
    stride_in_1x1=False,
)

# PointRend's heads: ``roi_heads.mask_head.{coarse,point}_head`` since detectron2 moved them into the mask
# head, ``roi_heads.mask_{coarse,point}_head`` in older files, whose coarse FCs are ``coarse_mask_fc1/2``.
_COARSE = r"roi_heads\.(?:mask_head\.coarse_head|mask_coarse_head)"
_POINT = r"roi_heads\.(?:mask_head\.point_head|mask_point_head)"

DETECTRON2_RCNN = Layout(
    name="detectron2 R-CNN (model zoo .pkl)",
    signature="backbone.bottom_up.stem.conv1.weight",
    rules=rules(
        _BATCH_COUNTER,
        (r"pixel_(?:mean|std)", None),  # the input convention, handled by folding it into conv1
        (r"proposal_generator\.anchor_generator\.cell_anchors\.\d+", None),  # recomputed from the config
        (r"backbone\.bottom_up\.stem\.conv1\.weight", CONV1),
        (r"backbone\.bottom_up\.stem\.conv1\.norm\.(\w+)", r"backbone.bottom_up.bn1.\1"),
        (
            r"backbone\.bottom_up\.res([2-5])\.(\d+)\.conv([1-3])\.weight",
            lambda m: f"{_stage(m)}.{m[2]}.conv{m[3]}.weight",
        ),
        (
            r"backbone\.bottom_up\.res([2-5])\.(\d+)\.conv([1-3])\.norm\.(\w+)",
            lambda m: f"{_stage(m)}.{m[2]}.bn{m[3]}.{m[4]}",
        ),
        (
            r"backbone\.bottom_up\.res([2-5])\.(\d+)\.shortcut\.weight",
            lambda m: f"{_stage(m)}.{m[2]}.downsample.0.weight",
        ),
        (
            r"backbone\.bottom_up\.res([2-5])\.(\d+)\.shortcut\.norm\.(\w+)",
            lambda m: f"{_stage(m)}.{m[2]}.downsample.1.{m[3]}",
        ),
        (
            r"backbone\.fpn_lateral([2-5])\.(weight|bias)",
            lambda m: f"backbone.fpn.lateral_convs.{int(m[1]) - 2}.{m[2]}",
        ),
        (r"backbone\.fpn_output([2-5])\.(weight|bias)", lambda m: f"backbone.fpn.output_convs.{int(m[1]) - 2}.{m[2]}"),
        (
            r"proposal_generator\.rpn_head\.(conv|objectness_logits|anchor_deltas)\.(weight|bias)",
            r"proposal_generator.head.\1.\2",
        ),
        (r"roi_heads\.box_head\.fc(\d)\.(weight|bias)", lambda m: f"roi_heads.box_head.fcs.{int(m[1]) - 1}.{m[2]}"),
        (r"roi_heads\.box_predictor\.(cls_score|bbox_pred)\.(weight|bias)", r"roi_heads.box_predictor.\1.\2"),
        (
            r"roi_heads\.mask_head\.mask_fcn(\d)\.(weight|bias)",
            lambda m: f"roi_heads.mask_head.convs.{int(m[1]) - 1}.{m[2]}",
        ),
        (r"roi_heads\.mask_head\.(deconv|predictor)\.(weight|bias)", r"roi_heads.mask_head.\1.\2"),
        (rf"{_COARSE}\.reduce_spatial_dim_conv\.(weight|bias)", r"roi_heads.mask_head.coarse_head.conv.\1"),
        (
            rf"{_COARSE}\.(?:coarse_mask_)?fc(\d)\.(weight|bias)",
            lambda m: f"roi_heads.mask_head.coarse_head.fcs.{int(m[1]) - 1}.{m[2]}",
        ),
        (rf"{_COARSE}\.prediction\.(weight|bias)", r"roi_heads.mask_head.coarse_head.predictor.\1"),
        (rf"{_POINT}\.fc(\d)\.(weight|bias)", lambda m: f"roi_heads.mask_head.point_head.fcs.{int(m[1]) - 1}.{m[2]}"),
        (rf"{_POINT}\.predictor\.(weight|bias)", r"roi_heads.mask_head.point_head.predictor.\1"),
    ),
    stride_in_1x1=True,
    caffe2_pixels=True,
)

_C2_NORM = {"s": "weight", "b": "bias", "rm": "running_mean", "riv": "running_var"}
_C2_CONV = {"a": 1, "b": 2, "c": 3}

CAFFE2_RESNET = Layout(
    name="Caffe2/MSRA ImageNet ResNet (R-50.pkl)",
    signature="conv1_w",
    rules=rules(
        (r".+_momentum", None),  # optimizer state
        (r"conv1_w", CONV1),
        (r"res_conv1_bn_(s|b|rm|riv)", lambda m: f"backbone.bottom_up.bn1.{_C2_NORM[m[1]]}"),
        (r"res([2-5])_(\d+)_branch2([abc])_w", lambda m: f"{_stage(m)}.{m[2]}.conv{_C2_CONV[m[3]]}.weight"),
        (
            r"res([2-5])_(\d+)_branch2([abc])_bn_(s|b|rm|riv)",
            lambda m: f"{_stage(m)}.{m[2]}.bn{_C2_CONV[m[3]]}.{_C2_NORM[m[4]]}",
        ),
        (r"res([2-5])_(\d+)_branch1_w", lambda m: f"{_stage(m)}.{m[2]}.downsample.0.weight"),
        (r"res([2-5])_(\d+)_branch1_bn_(s|b|rm|riv)", lambda m: f"{_stage(m)}.{m[2]}.downsample.1.{_C2_NORM[m[3]]}"),
        (r"(?:fc1000|pred)_w", "backbone.bottom_up.fc.weight"),
        (r"(?:fc1000|pred)_b", "backbone.bottom_up.fc.bias"),
    ),
    stride_in_1x1=True,
    caffe2_pixels=True,
    affine_norms=True,
)

LAYOUTS = {
    "torchvision": (TORCHVISION_MASK_RCNN, TORCHVISION_RESNET),
    "detectron2": (DETECTRON2_RCNN, CAFFE2_RESNET),
}
