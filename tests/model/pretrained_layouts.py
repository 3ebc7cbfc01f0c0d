"""Upstream checkpoint layouts, written out from the upstream module definitions (not from usl).

Each generator yields ``(file key, shape, usl MaskRCNN key or None, how)`` where ``how`` says how
the value must arrive: "same", "fold" (conv1 from BGR 0-255), "bg_last" (torchvision scores: row 0
moves to the end), "drop4" / "drop1" (torchvision background box deltas / mask dropped), "stat0" /
"stat1" (not in the file). ``None`` marks a tensor that must be reported unused.

Sources: torchvision/models/resnet.py, detection/{backbone_utils,rpn,faster_rcnn,mask_rcnn}.py and
ops/feature_pyramid_network.py (pre-0.13 names, as the COCO .pth files have them, or the
Conv2dNormActivation ``.0`` names of a newer state dict); detectron2/modeling/backbone/{resnet,fpn}.py,
proposal_generator/rpn.py, roi_heads/{box_head,fast_rcnn,mask_head}.py; Caffe2 blob names as
detectron2/checkpoint/c2_model_loading.py reads them.
"""

from __future__ import annotations

BLOCKS = (3, 4, 6, 3)  # ResNet-50
TV_NORM = ("weight", "bias", "running_mean", "running_var")


def _stages(width: int):
    """(stage 1..4, block, in channels, bottleneck width, out channels)."""
    channels = width
    for stage, count in enumerate(BLOCKS, start=1):
        planes = width * 2 ** (stage - 1)
        for block in range(count):
            yield stage, block, channels, planes, 4 * planes
            channels = 4 * planes


def torchvision_resnet50(width=64, prefix="", batch_counters=True, fc=True):
    def norm(name, channels):
        for param in TV_NORM:
            yield f"{prefix}{name}.{param}", (channels,), f"backbone.bottom_up.{name}.{param}", "same"
        if batch_counters:
            yield f"{prefix}{name}.num_batches_tracked", (), None, "same"

    yield f"{prefix}conv1.weight", (width, 3, 7, 7), "backbone.bottom_up.conv1.weight", "same"
    yield from norm("bn1", width)
    for stage, block, cin, planes, cout in _stages(width):
        base = f"layer{stage}.{block}"
        for k, shape in enumerate([(planes, cin, 1, 1), (planes, planes, 3, 3), (cout, planes, 1, 1)], start=1):
            yield f"{prefix}{base}.conv{k}.weight", shape, f"backbone.bottom_up.{base}.conv{k}.weight", "same"
            yield from norm(f"{base}.bn{k}", shape[0])
        if block == 0:
            yield (
                f"{prefix}{base}.downsample.0.weight",
                (cout, cin, 1, 1),
                f"backbone.bottom_up.{base}.downsample.0.weight",
                "same",
            )
            yield from norm(f"{base}.downsample.1", cout)
    if fc:
        yield f"{prefix}fc.weight", (1000, 32 * width), "backbone.bottom_up.fc.weight", "same"
        yield f"{prefix}fc.bias", (1000,), "backbone.bottom_up.fc.bias", "same"


def torchvision_maskrcnn(width=64, fpn=256, fc=1024, classes=91, new_names=False):
    """``classes`` includes torchvision's background (91 for COCO)."""
    yield from torchvision_resnet50(width, prefix="backbone.body.", batch_counters=False, fc=False)
    dot0 = ".0" if new_names else ""
    for i in range(4):
        cin = 4 * width * 2**i
        for param, shape in (("weight", (fpn, cin, 1, 1)), ("bias", (fpn,))):
            yield (
                f"backbone.fpn.inner_blocks.{i}{dot0}.{param}",
                shape,
                f"backbone.fpn.lateral_convs.{i}.{param}",
                "same",
            )
        for param, shape in (("weight", (fpn, fpn, 3, 3)), ("bias", (fpn,))):
            yield (
                f"backbone.fpn.layer_blocks.{i}{dot0}.{param}",
                shape,
                f"backbone.fpn.output_convs.{i}.{param}",
                "same",
            )
    conv = "conv.0.0" if new_names else "conv"
    for ours, theirs, out, k in (
        ("conv", conv, fpn, 3),
        ("objectness_logits", "cls_logits", 3, 1),
        ("anchor_deltas", "bbox_pred", 12, 1),
    ):
        yield f"rpn.head.{theirs}.weight", (out, fpn, k, k), f"proposal_generator.head.{ours}.weight", "same"
        yield f"rpn.head.{theirs}.bias", (out,), f"proposal_generator.head.{ours}.bias", "same"
    for index, (name, fan_in) in enumerate((("fc6", fpn * 49), ("fc7", fc))):
        yield f"roi_heads.box_head.{name}.weight", (fc, fan_in), f"roi_heads.box_head.fcs.{index}.weight", "same"
        yield f"roi_heads.box_head.{name}.bias", (fc,), f"roi_heads.box_head.fcs.{index}.bias", "same"
    yield (
        "roi_heads.box_predictor.cls_score.weight",
        (classes, fc),
        "roi_heads.box_predictor.cls_score.weight",
        "bg_last",
    )
    yield "roi_heads.box_predictor.cls_score.bias", (classes,), "roi_heads.box_predictor.cls_score.bias", "bg_last"
    yield (
        "roi_heads.box_predictor.bbox_pred.weight",
        (4 * classes, fc),
        "roi_heads.box_predictor.bbox_pred.weight",
        "drop4",
    )
    yield "roi_heads.box_predictor.bbox_pred.bias", (4 * classes,), "roi_heads.box_predictor.bbox_pred.bias", "drop4"
    for i in range(4):
        name = f"{i}.0" if new_names else f"mask_fcn{i + 1}"
        yield f"roi_heads.mask_head.{name}.weight", (fpn, fpn, 3, 3), f"roi_heads.mask_head.convs.{i}.weight", "same"
        yield f"roi_heads.mask_head.{name}.bias", (fpn,), f"roi_heads.mask_head.convs.{i}.bias", "same"
    yield "roi_heads.mask_predictor.conv5_mask.weight", (fpn, fpn, 2, 2), "roi_heads.mask_head.deconv.weight", "same"
    yield "roi_heads.mask_predictor.conv5_mask.bias", (fpn,), "roi_heads.mask_head.deconv.bias", "same"
    yield (
        "roi_heads.mask_predictor.mask_fcn_logits.weight",
        (classes, fpn, 1, 1),
        "roi_heads.mask_head.predictor.weight",
        "drop1",
    )
    yield "roi_heads.mask_predictor.mask_fcn_logits.bias", (classes,), "roi_heads.mask_head.predictor.bias", "drop1"


def detectron2_mask_rcnn(width=64, fpn=256, fc=1024, classes=80):
    """detectron2's GeneralizedRCNN state dict; ``classes`` without background (80 for COCO)."""

    def conv_norm(theirs, ours_conv, ours_norm, shape):
        yield f"backbone.bottom_up.{theirs}.weight", shape, f"backbone.bottom_up.{ours_conv}.weight", "same"
        for param in TV_NORM:
            yield (
                f"backbone.bottom_up.{theirs}.norm.{param}",
                (shape[0],),
                f"backbone.bottom_up.{ours_norm}.{param}",
                "same",
            )

    for key, shape, target, how in conv_norm("stem.conv1", "conv1", "bn1", (width, 3, 7, 7)):
        yield key, shape, target, "fold" if target.endswith("conv1.weight") else how
    for stage, block, cin, planes, cout in _stages(width):
        theirs, ours = f"res{stage + 1}.{block}", f"layer{stage}.{block}"
        for k, shape in enumerate([(planes, cin, 1, 1), (planes, planes, 3, 3), (cout, planes, 1, 1)], start=1):
            yield from conv_norm(f"{theirs}.conv{k}", f"{ours}.conv{k}", f"{ours}.bn{k}", shape)
        if block == 0:
            yield from conv_norm(
                f"{theirs}.shortcut", f"{ours}.downsample.0", f"{ours}.downsample.1", (cout, cin, 1, 1)
            )
    for level in range(2, 6):
        cin = 4 * width * 2 ** (level - 2)
        for kind, ours, shape in (
            ("lateral", "lateral_convs", (fpn, cin, 1, 1)),
            ("output", "output_convs", (fpn, fpn, 3, 3)),
        ):
            yield f"backbone.fpn_{kind}{level}.weight", shape, f"backbone.fpn.{ours}.{level - 2}.weight", "same"
            yield f"backbone.fpn_{kind}{level}.bias", (fpn,), f"backbone.fpn.{ours}.{level - 2}.bias", "same"
    for name, out, k in (("conv", fpn, 3), ("objectness_logits", 3, 1), ("anchor_deltas", 12, 1)):
        yield (
            f"proposal_generator.rpn_head.{name}.weight",
            (out, fpn, k, k),
            f"proposal_generator.head.{name}.weight",
            "same",
        )
        yield f"proposal_generator.rpn_head.{name}.bias", (out,), f"proposal_generator.head.{name}.bias", "same"
    yield "proposal_generator.anchor_generator.cell_anchors.0", (3, 4), None, "same"  # in older zoo files
    yield "pixel_mean", (3, 1, 1), None, "same"
    yield "pixel_std", (3, 1, 1), None, "same"
    for index, fan_in in enumerate((fpn * 49, fc)):
        yield f"roi_heads.box_head.fc{index + 1}.weight", (fc, fan_in), f"roi_heads.box_head.fcs.{index}.weight", "same"
        yield f"roi_heads.box_head.fc{index + 1}.bias", (fc,), f"roi_heads.box_head.fcs.{index}.bias", "same"
    for name, rows in (("cls_score", classes + 1), ("bbox_pred", 4 * classes)):
        yield f"roi_heads.box_predictor.{name}.weight", (rows, fc), f"roi_heads.box_predictor.{name}.weight", "same"
        yield f"roi_heads.box_predictor.{name}.bias", (rows,), f"roi_heads.box_predictor.{name}.bias", "same"
    for i in range(4):
        yield (
            f"roi_heads.mask_head.mask_fcn{i + 1}.weight",
            (fpn, fpn, 3, 3),
            f"roi_heads.mask_head.convs.{i}.weight",
            "same",
        )
        yield f"roi_heads.mask_head.mask_fcn{i + 1}.bias", (fpn,), f"roi_heads.mask_head.convs.{i}.bias", "same"
    for name, shape in (("deconv", (fpn, fpn, 2, 2)), ("predictor", (classes, fpn, 1, 1))):
        yield f"roi_heads.mask_head.{name}.weight", shape, f"roi_heads.mask_head.{name}.weight", "same"
        yield f"roi_heads.mask_head.{name}.bias", shape[:1], f"roi_heads.mask_head.{name}.bias", "same"


def caffe2_resnet50(width=64):
    """The MSRA ``R-50.pkl`` blobs: affine-only norms (``_bn_s``, ``_bn_b``), plus optimizer momenta."""

    def conv_bn(theirs, ours_conv, ours_norm, shape):
        yield f"{theirs}_w", shape, f"backbone.bottom_up.{ours_conv}.weight", "same"
        yield f"{theirs}_w_momentum", shape, None, "same"
        bn = theirs.replace("conv1", "res_conv1") if theirs == "conv1" else theirs
        yield f"{bn}_bn_s", shape[:1], f"backbone.bottom_up.{ours_norm}.weight", "same"
        yield f"{bn}_bn_b", shape[:1], f"backbone.bottom_up.{ours_norm}.bias", "same"
        yield None, shape[:1], f"backbone.bottom_up.{ours_norm}.running_mean", "stat0"
        yield None, shape[:1], f"backbone.bottom_up.{ours_norm}.running_var", "stat1"

    for key, shape, target, how in conv_bn("conv1", "conv1", "bn1", (width, 3, 7, 7)):
        yield key, shape, target, "fold" if key == "conv1_w" else how
    for stage, block, cin, planes, cout in _stages(width):
        theirs, ours = f"res{stage + 1}_{block}", f"layer{stage}.{block}"
        for k, letter, shape in (
            (1, "a", (planes, cin, 1, 1)),
            (2, "b", (planes, planes, 3, 3)),
            (3, "c", (cout, planes, 1, 1)),
        ):
            yield from conv_bn(f"{theirs}_branch2{letter}", f"{ours}.conv{k}", f"{ours}.bn{k}", shape)
        if block == 0:
            yield from conv_bn(f"{theirs}_branch1", f"{ours}.downsample.0", f"{ours}.downsample.1", (cout, cin, 1, 1))
    yield "fc1000_w", (1000, 32 * width), "backbone.bottom_up.fc.weight", "same"
    yield "fc1000_b", (1000,), "backbone.bottom_up.fc.bias", "same"
