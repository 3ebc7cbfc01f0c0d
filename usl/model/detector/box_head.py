"""Fast R-CNN box branch: 2 FC layers, class scores and class-specific box deltas."""

from __future__ import annotations

import itertools
from collections.abc import Sequence

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from usl.utils.transfer import to_device

from ..ops import Box2BoxTransform, batched_nms, kept_by_image
from .structures import Instances

Tensor = torch.Tensor

# detectron2's MODEL.ROI_BOX_HEAD defaults (detectron2/config/defaults.py), constants here: no recipe changes them
BBOX_REG_WEIGHTS = (10.0, 10.0, 5.0, 5.0)  # (dx, dy, dw, dh) scales of the box deltas
SMOOTH_L1_BETA = 0.0  # 0: the L1 loss


class FastRCNNFCHead(nn.Module):
    """Flatten pooled RoI features and apply ``num_fc`` ReLU FC layers (``fc_dim`` wide)."""

    def __init__(self, in_channels: int, resolution: int, num_fc: int, fc_dim: int):
        super().__init__()
        dims = [in_channels * resolution * resolution] + [fc_dim] * num_fc
        self.fcs = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:], strict=True))
        for fc in self.fcs:
            nn.init.kaiming_uniform_(fc.weight, a=1)
            nn.init.zeros_(fc.bias)
        self.output_dim = dims[-1]

    def forward(self, x: Tensor) -> Tensor:
        x = x.flatten(1)
        for fc in self.fcs:
            x = F.relu(fc(x))
        return x


class FastRCNNOutputLayers(nn.Module):
    """Scores over ``num_classes + 1`` (background is the LAST index) and 4 deltas per class."""

    def __init__(self, in_dim: int, num_classes: int):
        super().__init__()
        self.num_classes = num_classes
        self.cls_score = nn.Linear(in_dim, num_classes + 1)
        self.bbox_pred = nn.Linear(in_dim, num_classes * 4)
        nn.init.normal_(self.cls_score.weight, std=0.01)
        nn.init.normal_(self.bbox_pred.weight, std=0.001)
        nn.init.zeros_(self.cls_score.bias)
        nn.init.zeros_(self.bbox_pred.bias)
        self.box2box = Box2BoxTransform(BBOX_REG_WEIGHTS)

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor]:
        return self.cls_score(x), self.bbox_pred(x)

    def losses(
        self,
        logits: Tensor,
        deltas: Tensor,
        proposals: Sequence[Instances],
        num_foreground: Sequence[int] | None = None,
    ) -> dict[str, Tensor]:
        """Cross-entropy over sampled proposals and L1/smooth-L1 on foreground deltas of their class.

        Both are normalised by the number of sampled proposals (detectron2's choice).
        ``num_foreground``: each image's foreground count when its foreground rows come first (as
        the RoI heads sample them): the rows are then known without reading the device.
        """
        gt_classes = torch.cat([p.gt_classes for p in proposals])
        if gt_classes.numel() == 0:
            zero = logits.sum() * 0.0 + deltas.sum() * 0.0
            return {"loss_cls": zero, "loss_box_reg": zero}
        proposal_boxes = torch.cat([p.proposal_boxes for p in proposals])
        gt_boxes = torch.cat([p.gt_boxes for p in proposals])
        if num_foreground is None:
            foreground = torch.nonzero(gt_classes < self.num_classes).squeeze(1)
        else:
            starts = itertools.accumulate((len(p) for p in proposals[:-1]), initial=0)
            rows = [row for start, n in zip(starts, num_foreground, strict=True) for row in range(start, start + n)]
            foreground = to_device(rows, gt_classes.device, torch.long)  # one upload, queued without a wait
        predicted = deltas.view(len(deltas), self.num_classes, 4)[foreground, gt_classes[foreground]]
        target = self.box2box.get_deltas(proposal_boxes[foreground], gt_boxes[foreground])
        loss_box = F.smooth_l1_loss(predicted, target, beta=SMOOTH_L1_BETA, reduction="sum")
        return {"loss_cls": F.cross_entropy(logits, gt_classes), "loss_box_reg": loss_box / gt_classes.numel()}

    @torch.no_grad()
    def inference(
        self,
        logits: Tensor,
        deltas: Tensor,
        proposals: Sequence[Instances],
        score_thresh: float,
        nms_thresh: float,
        max_detections: int,
    ) -> list[Instances]:
        """Per image: decode every class's box, keep scores > ``score_thresh``, per-class NMS, top-k.

        All images in one NMS call, grouped by (image, class), so the host reads (the candidates,
        NMS's own, the detections per image) do not grow with the batch. Returns Instances with
        ``pred_boxes``, ``scores``, ``pred_classes``.
        """
        if not proposals:
            return []
        device, num_classes = logits.device, self.num_classes
        counts = [len(p) for p in proposals]
        image = to_device(np.repeat(np.arange(len(proposals)), counts), device)  # row -> image
        boxes = self.box2box.apply_deltas(deltas, torch.cat([p.proposal_boxes for p in proposals]))
        sizes = [(w, h, w, h) for h, w in (p.image_size for p in proposals)]
        limits = to_device(sizes, device, boxes.dtype)[image]  # clip_boxes with each row's image
        boxes = torch.minimum(boxes.view(-1, num_classes, 4).clamp(min=0), limits[:, None])
        scores = F.softmax(logits, dim=1)[:, :-1]
        finite = torch.isfinite(boxes).all(dim=2) & torch.isfinite(scores)
        rows, classes = torch.nonzero((scores > score_thresh) & finite, as_tuple=True)
        boxes, scores, image = boxes[rows, classes], scores[rows, classes], image[rows]
        kept = batched_nms(boxes, scores, image * num_classes + classes, nms_thresh)
        return [
            Instances(p.image_size, pred_boxes=boxes[keep], scores=scores[keep], pred_classes=classes[keep])
            for p, keep in zip(
                proposals, (k[:max_detections] for k in kept_by_image(kept, image, len(proposals))), strict=True
            )
        ]
