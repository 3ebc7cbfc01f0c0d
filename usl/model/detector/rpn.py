"""Region Proposal Network (Ren et al. 2015) over FPN levels, with its training losses."""

from __future__ import annotations

from collections.abc import Mapping

import torch
import torch.nn.functional as F
from torch import nn

from usl.utils.transfer import to_device

from ..backbone import ShapeSpec
from ..ops import AnchorGenerator, Box2BoxTransform, batched_nms, kept_by_image, nonempty_boxes, padded_match_quality
from .config import RPNConfig
from .matcher import IGNORE, Matcher, subsample_labels_dense
from .structures import ImageList, Instances

Tensor = torch.Tensor

# detectron2's MODEL.RPN defaults (detectron2/config/defaults.py), constants here: no recipe changes them
IOU_THRESHOLDS = (0.3, 0.7)  # anchors below: background, above: foreground, between: ignored
POSITIVE_FRACTION = 0.5  # at most this share of the sampled anchors is foreground
BBOX_REG_WEIGHTS = (1.0, 1.0, 1.0, 1.0)  # (dx, dy, dw, dh) scales of the box deltas
SMOOTH_L1_BETA = 0.0  # 0: the L1 loss
MIN_BOX_SIZE = 0.0  # proposals narrower than this are dropped (MIN_SIZE)
ANCHOR_OFFSET = 0.0  # anchor centres at the cells' top-left corners (ANCHOR_GENERATOR.OFFSET)


class RPNHead(nn.Module):
    """Shared 3x3 conv, then per anchor an objectness logit and 4 box deltas, on every level."""

    def __init__(self, channels: int, num_anchors: int):
        super().__init__()
        self.conv = nn.Conv2d(channels, channels, 3, padding=1)
        self.objectness_logits = nn.Conv2d(channels, num_anchors, 1)
        self.anchor_deltas = nn.Conv2d(channels, num_anchors * 4, 1)
        for layer in (self.conv, self.objectness_logits, self.anchor_deltas):
            nn.init.normal_(layer.weight, std=0.01)
            nn.init.zeros_(layer.bias)

    def forward(self, features: list[Tensor]) -> tuple[list[Tensor], list[Tensor]]:
        """Per level: logits (N, H*W*A) and deltas (N, H*W*A, 4), in the anchors' order."""
        logits, deltas = [], []
        for x in features:
            hidden = F.relu(self.conv(x))
            n, _, h, w = x.shape
            logits.append(self.objectness_logits(hidden).permute(0, 2, 3, 1).reshape(n, -1))
            deltas.append(self.anchor_deltas(hidden).view(n, -1, 4, h, w).permute(0, 3, 4, 1, 2).reshape(n, -1, 4))
        return logits, deltas


class RPN(nn.Module):
    """Proposes class-agnostic boxes; in training also returns ``loss_rpn_cls`` and ``loss_rpn_loc``."""

    def __init__(self, cfg: RPNConfig, input_shape: Mapping[str, ShapeSpec]):
        super().__init__()
        self.cfg = cfg
        self.in_features = list(cfg.in_features)
        shapes = [input_shape[name] for name in self.in_features]
        if len({s.channels for s in shapes}) != 1:
            raise ValueError(f"RPN levels must share a channel count, got {shapes}")
        self.anchor_generator = AnchorGenerator(
            cfg.anchors.sizes, cfg.anchors.aspect_ratios, [s.stride for s in shapes], ANCHOR_OFFSET
        )
        num_anchors = set(self.anchor_generator.num_anchors_per_location)
        if len(num_anchors) != 1:
            raise ValueError("every RPN level needs the same number of anchors per location")
        self.head = RPNHead(shapes[0].channels, num_anchors.pop())
        low, high = IOU_THRESHOLDS
        self.matcher = Matcher([low, high], [0, IGNORE, 1], allow_low_quality_matches=True)
        self.box2box = Box2BoxTransform(BBOX_REG_WEIGHTS)

    def forward(
        self, images: ImageList, features: Mapping[str, Tensor], targets: list[Instances] | None = None
    ) -> tuple[list[Instances], dict[str, Tensor]]:
        """Proposals (fields ``proposal_boxes``, ``objectness_logits``) per image, and losses.

        ``targets`` (fields ``gt_boxes``) are needed in training only.
        """
        maps = [features[name] for name in self.in_features]
        anchors = self.anchor_generator([m.shape[-2:] for m in maps])
        logits, deltas = self.head(maps)
        losses = {}
        if self.training:
            if targets is None:
                raise ValueError("RPN needs targets in training mode")
            losses = self.losses(torch.cat(anchors), torch.cat(logits, 1), torch.cat(deltas, 1), targets)
        proposals = self.select_proposals(anchors, logits, deltas, images.image_sizes)
        return proposals, losses

    @torch.no_grad()
    def label_anchors(self, anchors: Tensor, targets: list[Instances]) -> tuple[Tensor, Tensor]:
        """Sampled anchor labels (N, A) in {-1, 0, 1} and matched gt boxes (N, A, 4), every image's
        ground truth matched at once (padded with rows that match nothing)."""
        gt_boxes, quality = padded_match_quality([target.gt_boxes for target in targets], anchors[None])
        matches, labels = self.matcher(quality)
        if gt_boxes.shape[1]:
            matched_boxes = torch.gather(gt_boxes, 1, matches[..., None].expand(-1, -1, 4))
        else:
            matched_boxes = anchors.new_zeros(len(targets), *anchors.shape)
        labels = subsample_labels_dense(labels, self.cfg.batch_size_per_image, POSITIVE_FRACTION)
        return labels, matched_boxes

    def losses(self, anchors: Tensor, logits: Tensor, deltas: Tensor, targets: list[Instances]) -> dict[str, Tensor]:
        """Sums over all anchors weighted by their sampled labels (no boolean indexing, so no device read)."""
        labels, matched_boxes = self.label_anchors(anchors, targets)
        positive = labels == 1
        valid = labels != IGNORE
        # anchors that match nothing regress onto themselves (zero deltas, weight 0): finite everywhere
        anchors = anchors.expand_as(matched_boxes)
        matched_boxes = torch.where(positive[..., None], matched_boxes, anchors)
        target_deltas = self.box2box.get_deltas(anchors.reshape(-1, 4), matched_boxes.reshape(-1, 4))
        normalizer = self.cfg.batch_size_per_image * len(targets)
        loc = F.smooth_l1_loss(deltas.reshape(-1, 4), target_deltas, beta=SMOOTH_L1_BETA, reduction="none")
        loss_loc = (loc.sum(dim=1) * positive.reshape(-1)).sum()
        cls = F.binary_cross_entropy_with_logits(logits, labels.clamp(min=0).to(logits.dtype), reduction="none")
        loss_cls = (cls * valid).sum()
        weight = 1.0 / normalizer
        return {"loss_rpn_cls": loss_cls * weight, "loss_rpn_loc": loss_loc * weight}

    @torch.no_grad()
    def select_proposals(
        self, anchors: list[Tensor], logits: list[Tensor], deltas: list[Tensor], image_sizes: list[tuple[int, int]]
    ) -> list[Instances]:
        """Top-k per level, decode, clip, drop empty boxes, NMS per level, top-k per image."""
        pre_topk = self.cfg.pre_nms_topk_train if self.training else self.cfg.pre_nms_topk_test
        post_topk = self.cfg.post_nms_topk_train if self.training else self.cfg.post_nms_topk_test
        top_deltas, top_anchors, scores, levels = [], [], [], []
        for level, (level_anchors, level_logits, level_deltas) in enumerate(zip(anchors, logits, deltas, strict=True)):
            k = min(pre_topk, level_logits.shape[1])
            top_logits, top_index = level_logits.topk(k, dim=1)
            rows = torch.arange(level_logits.shape[0], device=top_index.device)[:, None]
            top_deltas.append(level_deltas[rows, top_index])
            top_anchors.append(level_anchors[top_index])
            scores.append(top_logits)
            levels.append(torch.full((k,), level, device=top_index.device, dtype=torch.long))
        # every level decoded at once
        top_anchors = torch.cat(top_anchors, 1)
        boxes = self.box2box.apply_deltas(torch.cat(top_deltas, 1).reshape(-1, 4), top_anchors.reshape(-1, 4))
        boxes, scores, levels = boxes.view(top_anchors.shape), torch.cat(scores, 1), torch.cat(levels)

        return self._nms_per_image(boxes, scores, levels, image_sizes, post_topk)

    def _nms_per_image(
        self, boxes: Tensor, scores: Tensor, levels: Tensor, image_sizes: list[tuple[int, int]], post_topk: int
    ) -> list[Instances]:
        """Clip, drop empty boxes, NMS per (image, level) and top-k per image, for all images in one
        NMS call: two host reads (the boxes kept, the count per image) whatever the batch size."""
        num_images, per_image = scores.shape
        sizes = to_device(image_sizes, boxes.device, boxes.dtype)  # (N, 2) height, width
        high = sizes.flip(1).repeat(1, 2)[:, None]  # (N, 1, 4): width, height, width, height
        boxes = torch.minimum(boxes.clamp(min=0), high).reshape(-1, 4)
        scores = scores.reshape(-1)
        image = torch.arange(num_images, device=boxes.device).repeat_interleave(
            per_image, output_size=num_images * per_image
        )
        keep = nonempty_boxes(boxes, MIN_BOX_SIZE) & torch.isfinite(scores) & torch.isfinite(boxes).all(1)
        index = torch.nonzero(keep).squeeze(1)
        groups = image[index] * len(self.in_features) + levels.repeat(num_images)[index]
        kept = index[batched_nms(boxes[index], scores[index], groups, self.cfg.nms_thresh)]
        proposals = []
        for size, rows in zip(image_sizes, kept_by_image(kept, image, num_images), strict=True):
            rows = rows[:post_topk]
            proposals.append(Instances(size, proposal_boxes=boxes[rows], objectness_logits=scores[rows]))
        return proposals
