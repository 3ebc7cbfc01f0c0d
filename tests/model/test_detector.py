import statistics

import pytest
import torch

from tests.model.detection_scenes import make_dataset, recall_and_mask_iou
from usl.model.detector import DetectorConfig, InvalidTargetError, MaskRCNN

LOSS_NAMES = {"loss_rpn_cls", "loss_rpn_loc", "loss_cls", "loss_box_reg", "loss_mask"}


def tiny_detector(seed: int = 0) -> MaskRCNN:
    torch.manual_seed(seed)
    return MaskRCNN(num_classes=2, cfg=DetectorConfig.tiny())


def test_training_losses_and_eval_output_shapes():
    images, targets = make_dataset(2, seed=1)
    sizes = [(128, 128), (120, 100)]
    targets[1] = {**targets[1], "masks": targets[1]["masks"][:, :120, :100]}
    detector = tiny_detector().train()
    losses = detector(images, sizes, targets)
    assert set(losses) == LOSS_NAMES
    assert all(v.dim() == 0 and torch.isfinite(v) for v in losses.values())
    sum(losses.values()).backward()
    assert detector.roi_heads.mask_head.predictor.weight.grad is not None

    detector.eval()
    with torch.no_grad():
        outputs = detector(images, sizes)
    for output, (h, w) in zip(outputs, sizes, strict=True):
        count = len(output["boxes"])
        assert 0 < count <= detector.cfg.roi_heads.detections_per_image
        assert output["boxes"].shape == (count, 4) and output["scores"].shape == (count,)
        assert output["labels"].dtype == torch.long and output["labels"].max() < 2
        assert output["masks"].shape == (count, h, w) and output["masks"].dtype == torch.bool
        assert (output["boxes"][:, 2] <= w).all() and (output["boxes"][:, 3] <= h).all()
        assert (output["scores"][:-1] >= output["scores"][1:]).all()


def test_a_model_built_on_the_detector_gets_what_forward_computes_through_its_methods():
    """USLModel's interface: the backbone's maps (with their shapes), the heads' training losses on
    them, and detections without masks, each what ``forward`` computes."""
    images, targets = make_dataset(2, seed=2)
    detector = tiny_detector().train()
    image_list = detector.preprocess(images)
    features = detector.features(image_list)
    shapes = detector.feature_shapes()
    assert features.keys() == shapes.keys()
    assert all(
        m.shape[1:] == (shapes[n].channels, 128 // shapes[n].stride, 128 // shapes[n].stride)
        for n, m in features.items()
    )
    torch.manual_seed(0)  # the RPN and the RoI heads sample anchors and proposals
    losses = detector.losses(image_list, features, targets)
    torch.manual_seed(0)
    assert losses == detector(images, targets=targets)
    with pytest.raises(RuntimeError, match="needs eval mode"):
        detector.detect_boxes(image_list, features)
    detector.eval()
    with torch.no_grad():
        detections = detector.detect_boxes(image_list, detector.features(image_list))
        outputs = detector(images)
    for found, output in zip(detections, outputs, strict=True):
        assert not found.has("pred_masks") and torch.equal(found.pred_boxes, output["boxes"])
        assert torch.equal(found.scores, output["scores"]) and torch.equal(found.pred_classes, output["labels"])


def test_parts_are_reusable_for_extra_heads():
    images, _ = make_dataset(2, seed=2)
    detector = tiny_detector().eval()
    features = detector.features(detector.preprocess(images))
    boxes = [torch.tensor([[10.0, 10.0, 50.0, 60.0]]), torch.tensor([[0.0, 0.0, 128.0, 128.0], [5.0, 5.0, 9.0, 9.0]])]
    pooled = detector.roi_heads.box_pooler(features, boxes)
    assert pooled.shape == (3, 32, 7, 7)


def test_images_without_objects_and_without_detections():
    images, _ = make_dataset(2, seed=4)
    empty = {
        "boxes": torch.zeros(0, 4),
        "labels": torch.zeros(0, dtype=torch.long),
        "masks": torch.zeros(0, 128, 128, dtype=torch.bool),
    }
    detector = tiny_detector().train()
    losses = detector(images, targets=[empty, empty])
    assert all(torch.isfinite(v) for v in losses.values())
    assert losses["loss_box_reg"] == 0 and losses["loss_mask"] == 0 and losses["loss_rpn_loc"] == 0
    sum(losses.values()).backward()

    detector.roi_heads.cfg.score_thresh_test = 1.0  # softmax scores never exceed it
    with torch.no_grad():
        outputs = detector.eval()(images)
    assert outputs[0]["boxes"].shape == (0, 4) and outputs[0]["masks"].shape == (0, 128, 128)


def test_invalid_targets_are_reported():
    images, targets = make_dataset(1, seed=3)
    detector = tiny_detector().train()
    with pytest.raises(InvalidTargetError, match="labels must lie in"):
        detector(images, targets=[{**targets[0], "labels": targets[0]["labels"] + 5}])
    with pytest.raises(InvalidTargetError, match="masks must be"):
        detector(images, targets=[{**targets[0], "masks": targets[0]["masks"][:, :64]}])
    with pytest.raises(ValueError, match="needs targets"):
        detector(images)


def test_overfits_tiny_synthetic_dataset():
    """100 Adam steps on 4 images: losses fall and detections recover boxes and masks."""
    images, targets = make_dataset(4, seed=0)
    detector = tiny_detector()
    with torch.no_grad():
        chance_recall, chance_iou = recall_and_mask_iou(detector.eval()(images), targets)
    optimizer = torch.optim.Adam([p for p in detector.parameters() if p.requires_grad], lr=1e-3)
    detector.train()
    totals = []
    for _ in range(100):
        losses = detector(images, targets=targets)
        loss = sum(losses.values())
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        totals.append(loss.item())
    assert all(torch.isfinite(torch.tensor(totals)))
    # medians: Adam at a constant rate spikes now and then (where depends on the CPU's rounding)
    assert statistics.median(totals[-10:]) < 0.3 * statistics.median(totals[:5]), totals
    with torch.no_grad():
        recall, mask_iou = recall_and_mask_iou(detector.eval()(images), targets)
    assert chance_recall < 0.5 and chance_iou < 0.3
    assert recall >= 0.8 and mask_iou >= 0.6, (recall, mask_iou)
