"""Standard Mask R-CNN RoI heads: proposal sampling, the box branch and the mask branch.

Subclass :class:`StandardROIHeads` (and register it in ``ROI_HEADS``) to add branches;
``box_pooler`` / ``mask_pooler`` pool RoI features from the backbone's feature dict for
any boxes, and in training :meth:`label_and_sample_proposals` records which ground
truth each sampled proposal matched (``gt_index``).
"""

from __future__ import annotations

from collections.abc import Mapping

import torch
from torch import nn

from ..backbone import Registry, ShapeSpec
from ..ops import padded_match_quality, stack_padded
from .box_head import FastRCNNFCHead, FastRCNNOutputLayers
from .config import ROIHeadsConfig
from .mask_head import (
    MaskRCNNConvUpsampleHead,
    batch_mask_targets,
    mask_rcnn_loss,
    paste_masks_in_image,
    select_class_masks,
)
from .matcher import Matcher, label_counts, subsample_labels
from .point_rend import PointRendMaskHead, PointRendSettings
from .poolers import MultiScaleRoIAlign
from .structures import Instances

Tensor = torch.Tensor

ROI_HEADS = Registry("ROI heads")

# detectron2's MODEL.ROI_HEADS / ROI_BOX_HEAD / ROI_MASK_HEAD defaults (detectron2/config/defaults.py),
# constants here: no recipe changes them
IOU_THRESHOLD = 0.5  # proposals at or above it are foreground (IOU_THRESHOLDS)
POSITIVE_FRACTION = 0.25  # at most this share of the sampled proposals is foreground
CANONICAL_LEVEL = 4  # a box of canonical_box_size pools from this FPN level (FPN paper, eq. 1)
BOX_POOLER_RESOLUTION = 7  # RoIAlign output of the box head
BOX_NUM_FC = 2  # FC layers of the box head
MASK_POOLER_RESOLUTION = 14  # RoIAlign output of the mask head (masks are predicted at twice this)
POOLER_SAMPLING_RATIO = 0  # RoIAlign samples per bin: adaptive


@ROI_HEADS.register("standard")
class StandardROIHeads(nn.Module):
    """Box head and mask head over sampled proposals.

    ``forward`` returns ``(instances, losses)``: in training the sampled proposals (fields
    ``proposal_boxes``, ``gt_classes``, ``gt_boxes``, ``gt_index``) and the branch losses;
    in eval the detections (``pred_boxes``, ``scores``, ``pred_classes``, ``pred_masks``) and ``{}``.
    """

    def __init__(self, cfg: ROIHeadsConfig, num_classes: int, input_shape: Mapping[str, ShapeSpec]):
        super().__init__()
        self.cfg = cfg
        self.num_classes = num_classes
        shapes = [input_shape[name] for name in cfg.in_features]
        channels = shapes[0].channels
        strides = [s.stride for s in shapes]
        self.matcher = Matcher([IOU_THRESHOLD], [0, 1], allow_low_quality_matches=False)
        self.box_pooler = self._pooler(BOX_POOLER_RESOLUTION, strides)
        self.box_head = FastRCNNFCHead(channels, BOX_POOLER_RESOLUTION, BOX_NUM_FC, cfg.box_head.fc_dim)
        self.box_predictor = FastRCNNOutputLayers(self.box_head.output_dim, num_classes)
        self.build_mask_branch(input_shape)

    def build_mask_branch(self, input_shape: Mapping[str, ShapeSpec]) -> None:
        """Mask R-CNN's: RoIAlign per FPN level and a conv head with a 2x deconv (28 x 28 masks)."""
        mask_cfg = self.cfg.mask_head
        shapes = [input_shape[name] for name in self.cfg.in_features]
        strides = [s.stride for s in shapes]
        self.mask_pooler = self._pooler(MASK_POOLER_RESOLUTION, strides)
        self.mask_head = MaskRCNNConvUpsampleHead(
            shapes[0].channels, self.num_classes, mask_cfg.num_conv, mask_cfg.conv_dim
        )

    def _pooler(self, resolution: int, strides: list[int]) -> MultiScaleRoIAlign:
        cfg = self.cfg
        return MultiScaleRoIAlign(
            cfg.in_features, strides, resolution, POOLER_SAMPLING_RATIO, cfg.canonical_box_size, CANONICAL_LEVEL
        )

    def forward(
        self,
        features: Mapping[str, Tensor],
        proposals: list[Instances],
        targets: list[Instances] | None = None,
    ) -> tuple[list[Instances], dict[str, Tensor]]:
        if self.training:
            if targets is None:
                raise ValueError("ROI heads need targets in training mode")
            proposals, num_foreground = self.label_and_sample_proposals(proposals, targets)
            losses = self.forward_box(features, proposals, num_foreground)
            # each image's foreground rows come first, so a slice selects them: no device read
            foreground = [p[:n] for p, n in zip(proposals, num_foreground, strict=True)]
            losses.update(self.mask_losses(features, foreground, targets))
            return proposals, losses
        return self.forward_mask(features, self.forward_box(features, proposals)), {}

    @torch.no_grad()
    def label_and_sample_proposals(
        self, proposals: list[Instances], targets: list[Instances]
    ) -> tuple[list[Instances], list[int]]:
        """Match proposals (plus the gt boxes themselves) to gt and sample a fg/bg mix per image.

        Returns the samples, each image's foreground first, and how many foreground each has (host
        ints). Background proposals get class ``num_classes`` and ``gt_index`` -1.
        """
        candidates = [
            torch.cat([p.proposal_boxes, t.gt_boxes.to(p.proposal_boxes.dtype)])
            for p, t in zip(proposals, targets, strict=True)
        ]
        # every image matched at once: ground truth and candidates padded (padded gt rows match nothing)
        _, quality = padded_match_quality([t.gt_boxes for t in targets], stack_padded(candidates)[0])
        all_matches, all_labels = self.matcher(quality)
        matched = [
            (m[: len(boxes)], lab[: len(boxes)])
            for m, lab, boxes in zip(all_matches, all_labels, candidates, strict=True)
        ]
        counts = label_counts([labels for _, labels in matched])  # one host read for the batch's draws
        sampled, num_foreground = [], []
        for proposal, target, boxes, (matches, labels), count in zip(
            proposals, targets, candidates, matched, counts, strict=True
        ):
            positive, negative = subsample_labels(labels, self.cfg.batch_size_per_image, POSITIVE_FRACTION, count)
            keep = torch.cat([positive, negative])
            is_foreground = torch.arange(len(keep), device=keep.device) < len(positive)
            matched = matches[keep]
            if len(target):
                gt_classes = torch.where(is_foreground, target.gt_classes[matched], self.num_classes)
                gt_boxes = target.gt_boxes[matched]
            else:
                gt_classes = torch.full_like(matched, self.num_classes)
                gt_boxes = torch.zeros_like(boxes[keep])
            sampled.append(
                Instances(
                    proposal.image_size,
                    proposal_boxes=boxes[keep],
                    gt_classes=gt_classes,
                    gt_boxes=gt_boxes,
                    gt_index=torch.where(is_foreground, matched, -1),
                )
            )
            num_foreground.append(len(positive))
        return sampled, num_foreground

    def forward_box(
        self, features: Mapping[str, Tensor], proposals: list[Instances], num_foreground: list[int] | None = None
    ):
        """Training: box losses (``num_foreground``: each image's foreground count, its rows first); eval:
        detections after score threshold, per-class NMS and top-k."""
        pooled = self.box_pooler(features, [p.proposal_boxes for p in proposals])
        logits, deltas = self.box_predictor(self.box_head(pooled))
        if self.training:
            return self.box_predictor.losses(logits, deltas, proposals, num_foreground)
        cfg = self.cfg
        return self.box_predictor.inference(
            logits, deltas, proposals, cfg.score_thresh_test, cfg.nms_thresh_test, cfg.detections_per_image
        )

    def forward_mask(self, features: Mapping[str, Tensor], instances: list[Instances]) -> list[Instances]:
        """Adds ``pred_masks`` (bool, H x W) to the detections (in training :meth:`mask_losses` runs instead)."""
        probabilities = self.mask_probabilities(features, instances)
        for detections, probs in zip(instances, probabilities.split([len(d) for d in instances]), strict=True):
            detections.pred_masks = paste_masks_in_image(
                probs, detections.pred_boxes, detections.image_size, self.cfg.mask_threshold
            )
        return instances

    def mask_losses(
        self, features: Mapping[str, Tensor], foreground: list[Instances], targets: list[Instances]
    ) -> dict[str, Tensor]:
        """``loss_mask``: per-pixel cross-entropy of the 28 x 28 mask of each proposal's class."""
        mask_logits = self.mask_head(self.mask_pooler(features, [p.proposal_boxes for p in foreground]))
        resolution = mask_logits.shape[-1]
        classes = torch.cat([p.gt_classes for p in foreground])
        gt = batch_mask_targets(
            [t.gt_masks for t in targets],
            [p.gt_index for p in foreground],
            [p.proposal_boxes for p in foreground],
            resolution,
        )
        return {"loss_mask": mask_rcnn_loss(mask_logits, classes, gt)}

    def mask_probabilities(self, features: Mapping[str, Tensor], detections: list[Instances]) -> Tensor:
        """Box-relative foreground probabilities (R, M, M) of each detection's class, images concatenated."""
        mask_logits = self.mask_head(self.mask_pooler(features, [d.pred_boxes for d in detections]))
        return select_class_masks(mask_logits, torch.cat([d.pred_classes for d in detections]))


@ROI_HEADS.register("point_rend")
class PointRendROIHeads(StandardROIHeads):
    """Mask R-CNN's box branch with PointRend's mask branch (:mod:`.point_rend`, 224 x 224 masks)."""

    settings = PointRendSettings()  # detectron2's pointrend_rcnn_R_50_FPN: what its model-zoo weights need

    def build_mask_branch(self, input_shape: Mapping[str, ShapeSpec]) -> None:
        settings = self.settings
        if settings.in_feature not in input_shape:
            raise ValueError(f"PointRend reads {settings.in_feature!r}, the backbone has {sorted(input_shape)}")
        shape = input_shape[settings.in_feature]
        self.mask_head = PointRendMaskHead(shape.channels, shape.stride, self.num_classes, settings)

    def mask_losses(
        self, features: Mapping[str, Tensor], foreground: list[Instances], targets: list[Instances]
    ) -> dict[str, Tensor]:
        return self.mask_head.losses(features, foreground, targets)

    def mask_probabilities(self, features: Mapping[str, Tensor], detections: list[Instances]) -> Tensor:
        classes = torch.cat([d.pred_classes for d in detections])
        return self.mask_head.predict(features, [d.pred_boxes for d in detections], classes).sigmoid()


def build_roi_heads(cfg: ROIHeadsConfig, num_classes: int, input_shape: Mapping[str, ShapeSpec]) -> nn.Module:
    return ROI_HEADS.get(cfg.name)(cfg, num_classes, input_shape)
