import math

import cv2
import numpy as np
import pytest
import torch
import torch.nn.functional as F

from tests.model.detection_oracles import roi_align_loop, subsample_labels_read_per_image
from usl.model.detector import (
    ImageList,
    Instances,
    Matcher,
    MultiScaleRoIAlign,
    assign_boxes_to_levels,
    batch_mask_targets,
    label_counts,
    mask_targets,
    paste_masks_in_image,
    subsample_labels,
    subsample_labels_dense,
)
from usl.model.detector.box_head import FastRCNNOutputLayers
from usl.model.ops import box_iou, padded_match_quality, stack_padded
from usl.utils.op_count import count_ops


def test_level_assignment_follows_fpn_equation():
    sides = torch.tensor([224.0, 112.0, 111.0, 448.0, 1000.0, 10.0, 447.0])
    boxes = torch.stack([torch.zeros(7), torch.zeros(7), sides, sides], dim=1)
    expected = [min(max(math.floor(4 + math.log2(s / 224)), 2), 5) - 2 for s in sides.tolist()]
    assert assign_boxes_to_levels(boxes, 2, 5, 224.0, 4).tolist() == expected == [2, 1, 0, 3, 3, 0, 2]


def test_multiscale_pooler_pools_each_box_from_its_level():
    generator = torch.Generator().manual_seed(0)
    strides = [4, 8, 16]
    features = {
        f"p{i + 2}": torch.randn(2, 3, 64 // s, 64 // s, generator=generator, dtype=torch.float64)
        for i, s in enumerate(strides)
    }
    boxes = [
        torch.tensor([[2.0, 3.0, 14.0, 11.0], [0.0, 0.0, 60.0, 50.0]], dtype=torch.float64),
        torch.tensor([[10.0, 12.0, 40.0, 42.0]], dtype=torch.float64),
    ]
    pooler = MultiScaleRoIAlign(
        ["p2", "p3", "p4"], strides, output_size=3, sampling_ratio=2, canonical_box_size=32, canonical_level=3
    )
    pooled = pooler(features, boxes)
    for row, (image, box) in enumerate([(0, boxes[0][0]), (0, boxes[0][1]), (1, boxes[1][0])]):
        side = math.sqrt(float((box[2] - box[0]) * (box[3] - box[1])))
        level = min(max(math.floor(3 + math.log2(side / 32)), 2), 4)
        roi = torch.cat([torch.tensor([float(image)], dtype=torch.float64), box])[None]
        expected = roi_align_loop(features[f"p{level}"], roi, (3, 3), 1.0 / 2**level, 2, True)[0]
        torch.testing.assert_close(pooled[row], expected)


def test_matcher_bands_and_low_quality_matches():
    iou = torch.tensor([[0.9, 0.5, 0.2, 0.0], [0.1, 0.65, 0.25, 0.0]])
    matches, labels = Matcher([0.3, 0.7], [0, -1, 1], allow_low_quality_matches=False)(iou)
    assert matches.tolist() == [0, 1, 1, 0] and labels.tolist() == [1, -1, 0, 0]
    _, labels = Matcher([0.3, 0.7], [0, -1, 1], allow_low_quality_matches=True)(iou)
    assert labels.tolist() == [1, 1, 0, 0]  # gt 1's best prediction (0.65) is promoted
    matches, labels = Matcher([0.5], [0, 1])(torch.zeros(0, 3))
    assert labels.tolist() == [0, 0, 0]


@pytest.mark.parametrize("low_quality", [False, True])
def test_matching_a_padded_batch_of_images_equals_matching_image_by_image(low_quality):
    """padded_match_quality (the RPN's and the RoI heads' matching): every image's ground truth padded
    with rows that match nothing, against each image matched alone."""
    g = torch.Generator().manual_seed(2)

    def boxes(n):
        xy = torch.rand(n, 2, generator=g) * 50
        return torch.cat([xy, xy + 1 + torch.rand(n, 2, generator=g) * 30], dim=1)

    gt = [boxes(3), boxes(0), boxes(1), boxes(5)]
    predictions = [boxes(40), boxes(7), boxes(25), boxes(60)]
    predictions[2][:3] = gt[2]  # exact matches, and ties for the low-quality rule
    matcher = Matcher([0.3, 0.7], [0, -1, 1], allow_low_quality_matches=low_quality)
    padded_gt, quality = padded_match_quality(gt, stack_padded(predictions)[0])
    assert padded_gt.shape == (4, 5, 4) and quality.shape == (4, 5, 60)
    matches, labels = matcher(quality)
    for image, (t, p) in enumerate(zip(gt, predictions, strict=True)):
        expected_matches, expected_labels = matcher(box_iou(t, p))
        assert torch.equal(labels[image, : len(p)], expected_labels)
        assert torch.equal(matches[image, : len(p)], expected_matches)


def test_subsample_labels_respects_budget_and_fraction():
    torch.manual_seed(0)
    labels = torch.tensor([1] * 10 + [0] * 100 + [-1] * 5)
    positive, negative = subsample_labels(labels, 16, 0.25)
    assert len(positive) == 4 and len(negative) == 12
    assert (labels[positive] == 1).all() and (labels[negative] == 0).all()
    positive, negative = subsample_labels(torch.tensor([1, 0, 0]), 16, 0.5)
    assert len(positive) == 1 and len(negative) == 2


def test_subsampling_with_the_batch_counts_read_once_draws_as_per_image_reads():
    g = torch.Generator().manual_seed(1)
    images = [torch.randint(-1, 2, (n,), generator=g) for n in (0, 3, 40, 300)] + [torch.full((50,), 0)]
    counts = label_counts(images)
    assert counts == [(int((x == 1).sum()), int((x == 0).sum())) for x in images]
    for budget, fraction in ((16, 0.25), (512, 0.25), (8, 1.0)):
        torch.manual_seed(3)
        per_image = [subsample_labels_read_per_image(x, budget, fraction) for x in images]
        torch.manual_seed(3)
        with count_ops() as reads:
            drawn = [subsample_labels(x, budget, fraction, c) for x, c in zip(images, counts, strict=True)]
        assert reads.total_syncs == 0, reads.syncs
        for (positive, negative), (old_positive, old_negative) in zip(drawn, per_image, strict=True):
            assert torch.equal(positive, old_positive) and torch.equal(negative, old_negative)


def test_dense_subsampling_draws_the_same_sizes_uniformly_for_every_row():
    torch.manual_seed(0)
    labels = torch.stack([torch.tensor([1] * 10 + [0] * 100 + [-1] * 5), torch.tensor([1, 0, 0] + [-1] * 112)])
    counts = torch.zeros(labels.shape)
    for _ in range(400):
        sampled = subsample_labels_dense(labels, 16, 0.25)
        assert ((sampled == 1) <= (labels == 1)).all() and ((sampled == 0) <= (labels == 0)).all()
        assert (sampled == 1).sum(1).tolist() == [4, 1] and (sampled == 0).sum(1).tolist() == [12, 2]
        counts += sampled >= 0
    # every foreground anchor of row 0 is drawn 4/10 of the time, every background one 12/100
    assert (counts[0, :10] / 400 - 0.4).abs().max() < 0.1 and (counts[0, 10:110] / 400 - 0.12).abs().max() < 0.07


def test_paste_masks_matches_opencv_resize_inside_the_box():
    generator = torch.Generator().manual_seed(1)
    mask = torch.rand(28, 28, generator=generator)
    box = torch.tensor([[10.0, 20.0, 66.0, 104.0]])  # 56 x 84 px: scale 2 in x, 3 in y
    pasted = paste_masks_in_image(mask[None], box, (120, 90), threshold=None)[0]
    expected = cv2.resize(mask.numpy(), (56, 84), interpolation=cv2.INTER_LINEAR)
    # cv2 replicates the border, pasting fades to zero outside the box: compare off the edge pixel.
    np.testing.assert_allclose(pasted[21:103, 11:65].numpy(), expected[1:-1, 1:-1], atol=1e-5)
    outside = torch.ones(120, 90, dtype=torch.bool)
    outside[19:105, 9:67] = False
    assert pasted[outside].abs().max() < 1e-6  # (float rounding at the exact -1 grid edge)
    binary = paste_masks_in_image(mask[None], box, (120, 90), threshold=0.5)
    assert binary.dtype == torch.bool and torch.equal(binary[0], pasted >= 0.5)


def test_mask_targets_crop_the_matched_mask():
    masks = torch.zeros(2, 40, 40, dtype=torch.bool)
    masks[0, 10:30, 4:20] = True
    masks[1, :, 20:] = True
    boxes = torch.tensor([[4.0, 10.0, 20.0, 30.0], [4.0, 10.0, 36.0, 30.0], [12.0, 0.0, 28.0, 40.0]])
    targets = mask_targets(masks, torch.tensor([0, 0, 1]), boxes, 8)
    assert targets[0].all()
    assert targets[1][:, :4].all() and not targets[1][:, 4:].any()  # the mask fills the box's left half
    assert not targets[2][:, :4].any() and targets[2][:, 4:].all()


def test_batch_mask_targets_equal_one_call_per_image_with_one_read_per_mask_size():
    g = torch.Generator().manual_seed(5)
    sizes = [(40, 48), (40, 48), (32, 40), (40, 48), (40, 48)]
    counts = [3, 0, 2, 4, 1]  # masks per image; the second image has none (and so no boxes)
    masks = [torch.rand(k, h, w, generator=g) > 0.5 for k, (h, w) in zip(counts, sizes, strict=True)]
    boxes, index = [], []
    for k, (h, w) in zip(counts, sizes, strict=True):
        n = 2 * k
        xy = torch.rand(n, 2, generator=g) * torch.tensor([w, h]) * 0.7
        boxes.append(torch.cat([xy, xy + 1 + torch.rand(n, 2, generator=g) * 20], dim=1))
        index.append(torch.randint(0, max(k, 1), (n,), generator=g))
    per_image = torch.cat([mask_targets(m, i, b, 14) for m, i, b in zip(masks, index, boxes, strict=True) if len(b)])
    with count_ops() as count:
        batched = batch_mask_targets(masks, index, boxes, 14)
    assert torch.equal(batched, per_image)
    assert count.syncs == {"numpy": 2}  # one RoIAlign per mask size, not per image
    assert batch_mask_targets(masks[1:2], index[1:2], boxes[1:2], 14).shape == (0, 14, 14)


def test_instances_index_cat_and_validation():
    inst = Instances((10, 20), boxes=torch.zeros(3, 4), scores=torch.tensor([0.1, 0.9, 0.5]))
    top = inst[inst.scores > 0.3]
    assert len(top) == 2 and top.image_size == (10, 20) and top.scores.tolist() == pytest.approx([0.9, 0.5])
    assert len(Instances.cat([inst, top])) == 5 and len(inst[1]) == 1
    with pytest.raises(ValueError, match="rows"):
        inst.labels = torch.zeros(2)
    with pytest.raises(AttributeError, match="no field"):
        _ = inst.masks


def test_image_list_pads_to_divisibility():
    images = ImageList.from_tensor(torch.ones(2, 3, 50, 70), [(50, 70), (40, 33)], size_divisibility=32)
    assert images.tensor.shape == (2, 3, 64, 96) and images.image_sizes == [(50, 70), (40, 33)]
    assert images.tensor[:, :, 50:].abs().sum() == 0
    with pytest.raises(ValueError, match="does not fit"):
        ImageList.from_tensor(torch.ones(1, 3, 8, 8), [(9, 8)])


def test_rpn_losses_weighted_over_all_anchors_match_the_sampled_anchors_alone(monkeypatch):
    """The RPN's losses sum over every anchor weighted by its label; the oracle indexes the
    sampled anchors out first (a reference implementation), for values and gradients."""
    from usl.model.backbone import ShapeSpec
    from usl.model.detector.config import DetectorConfig
    from usl.model.detector.rpn import BBOX_REG_WEIGHTS, RPN
    from usl.model.ops import Box2BoxTransform

    cfg = DetectorConfig.tiny().rpn
    rpn = RPN(cfg, {name: ShapeSpec(channels=8, stride=2 ** (i + 2)) for i, name in enumerate(cfg.in_features)})
    generator = torch.Generator().manual_seed(0)
    anchors = torch.rand(50, 2, generator=generator) * 60
    anchors = torch.cat([anchors, anchors + 4 + torch.rand(50, 2, generator=generator) * 30], 1)
    labels = torch.randint(-1, 2, (2, 50), generator=generator)
    matched = anchors + torch.randn(2, 50, 4, generator=generator)
    monkeypatch.setattr(rpn, "label_anchors", lambda anchors, targets: (labels, matched))
    logits = torch.randn(2, 50, generator=generator, requires_grad=True)
    deltas = torch.randn(2, 50, 4, generator=generator, requires_grad=True)
    new = rpn.losses(anchors, logits, deltas, [None, None])
    new_grads = torch.autograd.grad(sum(new.values()), [logits, deltas])
    positive, valid = labels == 1, labels != -1
    target = Box2BoxTransform(BBOX_REG_WEIGHTS).get_deltas(anchors.expand_as(matched)[positive], matched[positive])
    weight = 1.0 / (cfg.batch_size_per_image * 2)
    old = {
        "loss_rpn_cls": F.binary_cross_entropy_with_logits(logits[valid], labels[valid].float(), reduction="sum"),
        "loss_rpn_loc": F.smooth_l1_loss(deltas[positive], target, beta=0.0, reduction="sum"),
    }
    old = {k: v * weight for k, v in old.items()}
    old_grads = torch.autograd.grad(sum(old.values()), [logits, deltas])
    for key in old:
        torch.testing.assert_close(new[key], old[key])
    for a, b in zip(new_grads, old_grads, strict=True):
        torch.testing.assert_close(a, b)


def test_rpn_nms_of_all_images_at_once_matches_one_image_at_a_time():
    """The former per-image loop (clip, drop empty, NMS per level, top-k) is the oracle."""
    from usl.model.backbone import ShapeSpec
    from usl.model.detector.config import DetectorConfig
    from usl.model.detector.rpn import MIN_BOX_SIZE, RPN
    from usl.model.ops import batched_nms, clip_boxes, nonempty_boxes

    cfg = DetectorConfig.tiny().rpn
    rpn = RPN(cfg, {name: ShapeSpec(channels=8, stride=2 ** (i + 2)) for i, name in enumerate(cfg.in_features)})
    generator = torch.Generator().manual_seed(2)
    num_levels, per_level = len(cfg.in_features), 40
    corner = torch.rand(3, num_levels * per_level, 2, generator=generator) * 90 - 10
    boxes = torch.cat([corner, corner + torch.rand(3, num_levels * per_level, 2, generator=generator) * 40], 2)
    boxes[0, 3] = float("nan")
    boxes[1, 5, 2:] = boxes[1, 5, :2]  # empty
    scores = torch.randn(3, num_levels * per_level, generator=generator).round(decimals=1)  # ties
    scores[2, 7] = float("-inf")
    levels = torch.arange(num_levels).repeat_interleave(per_level)
    sizes = [(64, 80), (48, 64), (64, 64)]
    new = rpn._nms_per_image(boxes, scores, levels, sizes, post_topk=25)
    for image, (image_boxes, image_scores, size) in enumerate(zip(boxes, scores, sizes, strict=True)):
        image_boxes = clip_boxes(image_boxes, size)
        keep = nonempty_boxes(image_boxes, MIN_BOX_SIZE) & torch.isfinite(image_scores)
        keep &= torch.isfinite(image_boxes).all(dim=1)
        image_boxes, image_scores, image_levels = image_boxes[keep], image_scores[keep], levels[keep]
        kept = batched_nms(image_boxes, image_scores, image_levels, cfg.nms_thresh)[:25]
        assert torch.equal(new[image].proposal_boxes, image_boxes[kept])
        assert torch.equal(new[image].objectness_logits, image_scores[kept])
        assert new[image].image_size == size


def test_box_losses_with_host_foreground_counts_equal_the_device_search_and_read_nothing():
    """The RoI heads sample each image's foreground first and know the counts: the box losses
    given them equal those that find the foreground rows with ``nonzero`` (values and gradients,
    bit for bit), without a host sync."""
    g = torch.Generator().manual_seed(0)
    head = FastRCNNOutputLayers(16, 3)
    proposals, counts = [], []
    for n, fg in ((7, 3), (5, 0), (6, 6)):
        boxes = torch.rand(n, 2, generator=g) * 50
        boxes = torch.cat([boxes, boxes + 5 + torch.rand(n, 2, generator=g) * 20], 1)
        classes = torch.cat([torch.randint(0, 3, (fg,), generator=g), torch.full((n - fg,), 3)])
        proposals.append(
            Instances(
                (80, 80), proposal_boxes=boxes, gt_boxes=boxes + torch.randn(n, 4, generator=g), gt_classes=classes
            )
        )
        counts.append(fg)
    x = torch.randn(18, 16, generator=g)
    results = []
    for num_foreground in (None, counts):
        head.zero_grad()
        logits, deltas = head(x)
        with count_ops() as count:
            losses = head.losses(logits, deltas, proposals, num_foreground)
        sum(losses.values()).backward()
        results.append((losses, head.bbox_pred.weight.grad.clone(), count.total_syncs))
    (device, device_grad, device_syncs), (host, host_grad, host_syncs) = results
    assert all(torch.equal(device[k], host[k]) for k in device) and torch.equal(device_grad, host_grad)
    assert device_syncs >= 1 and host_syncs == 0


def test_box_inference_of_all_images_at_once_matches_one_image_at_a_time_with_reads_per_batch():
    """The former per-image loop (decode, clip, threshold, per-class NMS, top-k) is the oracle;
    the batched call reads the device as often for one image as for four, on the torch paths."""
    from usl.model.ops import batched_nms, clip_boxes
    from usl.utils.compiled import torch_paths_only

    g = torch.Generator().manual_seed(3)
    head = FastRCNNOutputLayers(16, 3)
    sizes, counts = [(80, 96), (64, 64), (48, 80), (80, 80)], [30, 0, 25, 40]
    proposals = []
    for size, n in zip(sizes, counts, strict=True):
        corner = torch.rand(n, 2, generator=g) * 60 - 5
        proposals.append(
            Instances(size, proposal_boxes=torch.cat([corner, corner + 5 + torch.rand(n, 2, generator=g) * 30], 1))
        )
    with torch.no_grad():
        logits, deltas = head(torch.randn(sum(counts), 16, generator=g))
    logits = logits.round(decimals=1)  # tied scores
    deltas[3] = float("nan")
    new = head.inference(logits, deltas, proposals, 0.05, 0.5, 12)
    for image, (proposal, image_logits, image_deltas) in enumerate(
        zip(proposals, logits.split(counts), deltas.split(counts), strict=True)
    ):
        boxes = head.box2box.apply_deltas(image_deltas, proposal.proposal_boxes)
        boxes = clip_boxes(boxes.view(-1, 3, 4), proposal.image_size)
        scores = F.softmax(image_logits, dim=1)[:, :-1]
        finite = torch.isfinite(boxes).all(dim=2) & torch.isfinite(scores)
        rows, classes = torch.nonzero((scores > 0.05) & finite, as_tuple=True)
        boxes, scores = boxes[rows, classes], scores[rows, classes]
        keep = batched_nms(boxes, scores, classes, 0.5)[:12]
        assert torch.equal(new[image].pred_boxes, boxes[keep]) and torch.equal(new[image].scores, scores[keep])
        assert torch.equal(new[image].pred_classes, classes[keep]) and new[image].image_size == proposal.image_size
    assert sum(len(r) for r in new) > 12  # detections to compare
    syncs = []
    for images in (1, 4):
        rows = sum(counts[:images])
        with torch_paths_only(), count_ops() as count:
            head.inference(logits[:rows], deltas[:rows], proposals[:images], 0.05, 0.5, 12)
        syncs.append(count.total_syncs)
    assert syncs[0] == syncs[1], syncs
