"""model.init_weights: checkpoints written in each upstream key layout land where they should."""

import pickle
import warnings

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from tests.model.detection_scenes import make_dataset
from tests.model.pretrained_layouts import (
    caffe2_resnet50,
    detectron2_mask_rcnn,
    torchvision_maskrcnn,
    torchvision_resnet50,
)
from usl.model.backbone import IMAGENET_MEAN, IMAGENET_STD, BackboneConfig, FPNConfig, ResNetConfig
from usl.model.config import LayoutHeadConfig, LayoutRange, ModelConfig, ShapeHeadConfig
from usl.model.detector import BoxHeadConfig, DetectorConfig, MaskHeadConfig, MaskRCNN, ROIHeadsConfig
from usl.model.pretrained import WeightsError, init_detector, print_report
from usl.model.usl_model import USLModel

CAFFE2_MEAN_BGR = (103.530, 116.280, 123.675)  # detectron2's MODEL.PIXEL_MEAN for MSRA weights (std 1)


def write_checkpoint(tmp_path, entries, fmt, name, wrap=True, seed=0):
    """Random values (every tensor distinct) in the file format; returns (path, {file key: tensor})."""
    generator = torch.Generator().manual_seed(seed)
    tensors = {}
    for key, shape, _, _ in entries:
        if key is None:
            continue
        if key.endswith("num_batches_tracked"):
            tensors[key] = torch.tensor(7)
        elif key.endswith("running_var") or key.endswith("_riv"):
            tensors[key] = torch.rand(shape, generator=generator) + 0.5
        else:
            tensors[key] = torch.randn(shape, generator=generator)
    path = tmp_path / name
    if fmt == "torchvision":
        torch.save(tensors, path)
    else:
        arrays = {k: v.numpy() for k, v in tensors.items()}
        payload = {"model": arrays, "__author__": "Detectron2 Model Zoo"} if wrap else arrays
        with open(path, "wb") as stream:
            pickle.dump(payload, stream)
    return path, tensors


def detector_config(width=64, fpn=256, fc=1024, mask=256, stride_in_1x1=False, norm="FrozenBN", freeze_at=2):
    return DetectorConfig(
        backbone=BackboneConfig(
            resnet=ResNetConfig(50, width, norm, freeze_at, stride_in_1x1=stride_in_1x1), fpn=FPNConfig(fpn)
        ),
        roi_heads=ROIHeadsConfig(box_head=BoxHeadConfig(fc_dim=fc), mask_head=MaskHeadConfig(conv_dim=mask)),
    )


def expected_value(how, tensor, eps=1e-5):
    if how == "fold":  # usl input = (rgb - mean) / std; MSRA conv1 saw bgr * 255 - 255 * mean
        scale = 255 * torch.tensor(IMAGENET_STD, dtype=torch.float64)[None, :, None, None]
        return (tensor.double().flip(1) * scale).float()
    if how == "bg_last":
        return torch.cat([tensor[1:], tensor[:1]])
    return {"same": tensor, "drop4": tensor[4:], "drop1": tensor[1:]}[how]


def check_every_tensor_landed(model, entries, tensors, report):
    state = model.state_dict()
    unused = {key for key, _, target, _ in entries if target is None}
    assert set(report.unused) == unused
    landed = set()
    for key, shape, target, how in entries:
        if target is None:
            continue
        if how == "stat0":
            assert torch.equal(state[target], torch.zeros(shape)), target
        elif how == "stat1":  # affine-only norm: x * s + b exactly
            assert torch.equal(state[target], torch.full(shape, 1 - 1e-5)), target
        else:
            assert torch.equal(state[target], expected_value(how, tensors[key])), f"{key} -> {target}"
        landed.add(target)
    assert set(report.loaded) == landed


FULL_LAYOUTS = {
    "torchvision_maskrcnn_coco_pth": (lambda: list(torchvision_maskrcnn()), "torchvision", False, "model.pth"),
    "torchvision_maskrcnn_new_names": (
        lambda: list(torchvision_maskrcnn(new_names=True)),
        "torchvision",
        False,
        "new.pth",
    ),
    "detectron2_mask_rcnn_pkl": (lambda: list(detectron2_mask_rcnn()), "detectron2", True, "model_final.pkl"),
}


@pytest.mark.parametrize("name", FULL_LAYOUTS)
def test_full_mask_rcnn_checkpoints_land_everywhere(tmp_path, name):
    make_entries, fmt, msra, filename = FULL_LAYOUTS[name]
    entries = make_entries()
    path, tensors = write_checkpoint(tmp_path, entries, fmt, filename)
    # COCO has 80 categories (torchvision: 91 slots incl. background): the class layers fit and convert.
    num_classes = 90 if fmt == "torchvision" else 80
    model = MaskRCNN(num_classes, detector_config(stride_in_1x1=msra))
    report = init_detector(model, path)
    check_every_tensor_landed(model, entries, tensors, report)
    assert report.reinitialised == [] and report.folded_pixels == msra
    assert report.kept == {"backbone.bottom_up.fc": 2}  # detection files have no classifier


@pytest.mark.parametrize("fmt", ["torchvision", "detectron2"])
def test_class_layers_that_do_not_fit_are_reinitialised_and_reported(tmp_path, fmt, capsys):
    small = dict(width=8, fpn=16, fc=32)
    entries = list(torchvision_maskrcnn(**small) if fmt == "torchvision" else detectron2_mask_rcnn(**small))
    path, tensors = write_checkpoint(tmp_path, entries, fmt, "coco" + (".pth" if fmt == "torchvision" else ".pkl"))
    model = MaskRCNN(3, detector_config(**small, mask=16, stride_in_1x1=fmt == "detectron2"))
    before = {k: v.clone() for k, v in model.state_dict().items()}
    report = init_detector(model, path)
    class_keys = {
        f"roi_heads.{m}.{p}"
        for m in ("box_predictor.cls_score", "box_predictor.bbox_pred", "mask_head.predictor")
        for p in ("weight", "bias")
    }
    assert {entry.split(":")[0] for entry in report.reinitialised} == class_keys
    state = model.state_dict()
    for key in class_keys:
        assert torch.equal(state[key], before[key])
    others = [e for e in entries if e[2] not in class_keys]
    check_every_tensor_landed(model, others, tensors, report)
    print_report(report)
    printed = capsys.readouterr().err
    assert f"loaded {len(report.loaded)} tensors, re-initialised 6, unused {len(report.unused)}" in printed
    rows = 91 if fmt == "torchvision" else 81
    assert f"roi_heads.box_predictor.cls_score.weight: file ({rows}, 32) vs model (4, 32)" in printed


@pytest.mark.parametrize("layout", ["torchvision_resnet50", "caffe2_r50"])
def test_imagenet_backbones_fill_the_resnet_and_keep_the_rest(tmp_path, layout):
    if layout == "torchvision_resnet50":
        entries, fmt, name, msra = list(torchvision_resnet50()), "torchvision", "resnet50-0676ba61.pth", False
    else:
        entries, fmt, name, msra = list(caffe2_resnet50()), "detectron2", "R-50.pkl", True
    path, tensors = write_checkpoint(tmp_path, entries, fmt, name, wrap=False)
    model = MaskRCNN(3, detector_config(stride_in_1x1=msra))
    before = {k: v.clone() for k, v in model.state_dict().items()}
    report = init_detector(model, path)
    check_every_tensor_landed(model, entries, tensors, report)
    for key, value in model.state_dict().items():
        if not key.startswith("backbone.bottom_up."):
            assert torch.equal(value, before[key]), key
    assert set(report.kept) == {
        "backbone.fpn",
        "proposal_generator",
        "roi_heads.box_head",
        "roi_heads.box_predictor",
        "roi_heads.mask_head",
    }


def test_msra_stem_computes_what_it_computed_on_bgr_0_255_inputs(tmp_path):
    entries = list(caffe2_resnet50(width=8))
    path, tensors = write_checkpoint(tmp_path, entries, "detectron2", "R-50.pkl", wrap=False)
    model = MaskRCNN(2, detector_config(width=8, fpn=16, fc=32, mask=16, stride_in_1x1=True)).eval()
    init_detector(model, path)
    rgb = torch.rand(1, 3, 33, 47)
    bgr255 = rgb.flip(1) * 255 - torch.tensor(CAFFE2_MEAN_BGR)[None, :, None, None]
    caffe2 = F.conv2d(bgr255.double(), tensors["conv1_w"].double(), stride=2, padding=3)
    caffe2 = (
        caffe2 * tensors["res_conv1_bn_s"].double()[None, :, None, None]
        + tensors["res_conv1_bn_b"].double()[None, :, None, None]
    )
    normalised = (rgb - torch.tensor(IMAGENET_MEAN)[None, :, None, None]) / torch.tensor(IMAGENET_STD)[
        None, :, None, None
    ]
    resnet = model.backbone.bottom_up
    ours = resnet.bn1(resnet.conv1(normalised))
    torch.testing.assert_close(ours.double(), caffe2, rtol=1e-4, atol=1e-3)  # borders included (zero = mean in both)
    assert resnet.layer2[0].conv1.stride == (2, 2) and resnet.layer2[0].conv2.stride == (1, 1)  # MSRA: stride in 1x1


def test_frozen_stem_stays_bit_identical_through_a_training_step(tmp_path):
    entries = list(detectron2_mask_rcnn(width=8, fpn=16, fc=32, classes=2))
    path, _ = write_checkpoint(tmp_path, entries, "detectron2", "small.pkl")
    cfg = detector_config(width=8, fpn=16, fc=32, mask=16, stride_in_1x1=True, freeze_at=2)
    cfg.rpn.anchors.sizes = ((8,), (16,), (32,), (64,), (128,))
    model = MaskRCNN(2, cfg).train()
    init_detector(model, path)
    loaded = {k: v.clone() for k, v in model.state_dict().items()}
    images, targets = make_dataset(2, seed=3)
    optimizer = torch.optim.SGD([p for p in model.parameters() if p.requires_grad], lr=0.1, momentum=0.9)
    sum(model(images, targets=targets).values()).backward()
    optimizer.step()
    after = model.state_dict()
    frozen = [
        k
        for k in after
        if k.startswith(("backbone.bottom_up.conv1", "backbone.bottom_up.bn1", "backbone.bottom_up.layer1."))
    ]
    assert len(frozen) > 40
    for key in frozen:
        assert torch.equal(after[key], loaded[key]), key
    assert not torch.equal(
        after["backbone.bottom_up.layer2.0.conv1.weight"], loaded["backbone.bottom_up.layer2.0.conv1.weight"]
    )
    assert not torch.equal(after["roi_heads.box_head.fcs.0.weight"], loaded["roi_heads.box_head.fcs.0.weight"])


def test_unknown_keys_shape_mismatches_and_gaps_are_errors_naming_the_key(tmp_path):
    small = dict(width=8, fpn=16, fc=32, mask=16)
    entries = list(detectron2_mask_rcnn(width=8, fpn=16, fc=32, classes=2))
    model = lambda **kw: MaskRCNN(2, detector_config(**{**small, "stride_in_1x1": True, **kw}))  # noqa: E731

    extra = entries + [("roi_heads.keypoint_head.conv_fcn1.weight", (4, 4), None, "same")]
    path, _ = write_checkpoint(tmp_path, extra, "detectron2", "extra.pkl")
    with pytest.raises(
        WeightsError, match=r"extra.pkl: key 'roi_heads.keypoint_head.conv_fcn1.weight' maps to nothing"
    ):
        init_detector(model(), path)

    path, _ = write_checkpoint(tmp_path, entries, "detectron2", "ok.pkl")
    with pytest.raises(
        WeightsError,
        match=r"ok.pkl: 'backbone.fpn_lateral2.weight' has shape \(16, 32, 1, 1\) but 'backbone.fpn.lateral_convs.0.weight' is \(32, 32, 1, 1\)",
    ):
        init_detector(model(fpn=32), path)
    with pytest.raises(WeightsError, match=r"stride on the first 1x1 conv.*stride_in_1x1=true"):
        init_detector(model(stride_in_1x1=False), path)

    gap = [e for e in entries if e[0] != "roi_heads.mask_head.mask_fcn3.bias"]
    path, _ = write_checkpoint(tmp_path, gap, "detectron2", "gap.pkl")
    with pytest.raises(
        WeightsError, match=r"gap.pkl lacks 1 tensor\(s\) of parts it provides: roi_heads.mask_head.convs.2.bias"
    ):
        init_detector(model(), path)

    resnet101 = entries + [("backbone.bottom_up.res4.6.conv1.weight", (16, 128, 1, 1), None, "same")]
    path, _ = write_checkpoint(tmp_path, resnet101, "detectron2", "r101.pkl")
    with pytest.raises(
        WeightsError,
        match=r"'backbone.bottom_up.res4.6.conv1.weight' maps to 'backbone.bottom_up.layer3.6.conv1.weight', which this model does not have",
    ):
        init_detector(model(), path)

    not_weights = tmp_path / "classes.pkl"
    with open(not_weights, "wb") as stream:
        pickle.dump({"model": {"x": np.zeros(2)}, "hook": warnings.warn}, stream)
    with pytest.raises(WeightsError, match=r"classes.pkl could not be read.*refusing to load"):
        init_detector(model(), not_weights)
    with pytest.raises(WeightsError, match="nowhere.pth does not exist"):
        init_detector(model(), tmp_path / "nowhere.pth")


def test_model_config_resolves_the_resnet_variant():
    assert ModelConfig(init_weights="/w/R-50.pkl").detector.backbone.resnet.stride_in_1x1 is True
    assert ModelConfig(init_weights="/w/resnet50.pth").detector.backbone.resnet.stride_in_1x1 is False
    assert ModelConfig().detector.backbone.resnet.stride_in_1x1 is None  # built as v1.5 (torchvision)
    explicit = DetectorConfig()
    explicit.backbone.resnet.stride_in_1x1 = False
    assert ModelConfig(detector=explicit, init_weights="/w/R-50.pkl").detector.backbone.resnet.stride_in_1x1 is False


def test_usl_model_starts_from_init_weights_and_checkpoint_loading_skips_them(tmp_path, capsys):
    entries = list(detectron2_mask_rcnn(width=8, fpn=16, fc=32, classes=2))
    path, tensors = write_checkpoint(tmp_path, entries, "detectron2", "coco_small.pkl")
    detector = detector_config(width=8, fpn=16, fc=32, mask=16, stride_in_1x1=None)
    cfg = ModelConfig(
        detector=detector,
        categories=("chair", "table"),
        layout_range=LayoutRange(1.0, 5.0, 0.1, 1.0),
        shape=ShapeHeadConfig(ico_level=1, num_stages=1, hidden_dim=16),
        layout=LayoutHeadConfig(fc_dim=16),
        init_weights=str(path),
    )
    model = USLModel(cfg)
    assert model.detector.backbone.bottom_up.stride_in_1x1  # resolved from the .pkl
    assert torch.equal(model.detector.roi_heads.box_head.fcs[1].weight, tensors["roi_heads.box_head.fc2.weight"])
    assert "coco_small.pkl (detectron2 R-CNN (model zoo .pkl)): loaded" in capsys.readouterr().err
    path.unlink()  # e.g. evaluating on another machine: the checkpoint's state dict replaces them anyway
    USLModel(cfg, load_init_weights=False)
