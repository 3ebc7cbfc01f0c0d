"""PointRend's mask branch (Kirillov et al., CVPR 2020): a coarse mask, then point-wise refinement.

The layers and the inference procedure follow detectron2's ``projects/PointRend`` for
``pointrend_rcnn_R_50_FPN_3x_coco`` so its model-zoo weights compute the same masks here:

* the coarse head samples p2 on a regular 14 x 14 grid per box (bilinear, like ``grid_sample``:
  zero outside the map), reduces it with a 2 x 2 stride-2 conv, two FC layers and a linear layer to
  7 x 7 logits per class;
* the point head is an MLP (1-wide convs) over the bilinearly sampled p2 feature of each point plus
  the coarse logits at that point, which are fed again to every layer;
* inference predicts a regular 28 x 28 grid of points, then three times upsamples the logits 2x and
  re-predicts the 784 most uncertain cells (logit nearest 0): 224 x 224 masks.

Every step runs on all instances of all images at once; only feature sampling loops over images
(each image has its own feature map). Points are ``(x, y)`` in ``[0, 1]^2`` box-relative coordinates.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from .mask_head import batch_mask_targets, mask_rcnn_loss
from .structures import Instances

Tensor = torch.Tensor


@dataclass(frozen=True)
class PointRendSettings:
    """The sizes of detectron2's ``pointrend_rcnn_R_50_FPN`` (``MODEL.POINT_HEAD`` and
    ``MODEL.ROI_MASK_HEAD``): fixed, since they are what its model-zoo weights were trained with."""

    in_feature: str = "p2"  # both heads read the finest FPN level
    pooler_resolution: int = 14  # the coarse head's regular grid of samples per box
    conv_dim: int = 256
    num_fc: int = 2
    fc_dim: int = 1024
    coarse_resolution: int = 7
    point_num_fc: int = 3
    point_fc_dim: int = 256
    train_num_points: int = 14 * 14
    oversample_ratio: int = 3  # training: candidates per point (k in the paper)
    importance_sample_ratio: float = 0.75  # training: share of points picked by uncertainty (beta)
    subdivision_steps: int = 5  # inference: each doubles the resolution (7 -> 224)
    subdivision_num_points: int = 28 * 28  # inference: cells re-predicted per step


def point_sample(maps: Tensor, points: Tensor) -> Tensor:
    """Bilinear samples (N, C, P) of maps (N, C, H, W) at points (N, P, 2) in ``[0, 1]^2`` of the map.

    ``grid_sample`` without corner alignment: 0 and 1 are the outer edges of the border pixels, and
    samples fade to zero beyond the pixel centres at the border.
    """
    grid = (2.0 * points - 1.0).unsqueeze(2).to(maps.dtype)
    return F.grid_sample(maps, grid, mode="bilinear", align_corners=False).squeeze(3)


def regular_grid(side: int, count: int, device: torch.device) -> Tensor:
    """Cell centres of a ``side`` x ``side`` grid, row-major, for ``count`` boxes: (count, side^2, 2)."""
    centres = (torch.arange(side, device=device, dtype=torch.float32) + 0.5) / side
    y, x = torch.meshgrid(centres, centres, indexing="ij")
    return torch.stack([x.reshape(-1), y.reshape(-1)], dim=1).expand(count, -1, -1)


def points_in_image(boxes: Tensor, points: Tensor) -> Tensor:
    """Box-relative points (R, P, 2) to image pixels for boxes (R, 4) xyxy."""
    return boxes[:, None, :2] + points * (boxes[:, None, 2:] - boxes[:, None, :2])


def sample_box_points(feature: Tensor, stride: int, boxes: list[Tensor], points: Tensor) -> Tensor:
    """Features (R, C, P) of a feature map (N, C, H, W) at box-relative points of each image's boxes."""
    image_points = points_in_image(torch.cat(boxes), points)
    size = feature.new_tensor([feature.shape[3] * stride, feature.shape[2] * stride])
    sampled = []
    for image, image_points_part in enumerate(image_points.split([len(b) for b in boxes])):
        rows, count = image_points_part.shape[:2]
        if rows == 0:
            continue
        flat = (image_points_part / size).reshape(1, rows * count, 2)
        values = point_sample(feature[image : image + 1], flat)[0]  # (C, rows * count)
        sampled.append(values.view(-1, rows, count).transpose(0, 1))
    if not sampled:
        return feature.new_zeros((0, feature.shape[1], points.shape[1]))
    return torch.cat(sampled)


def uncertainty(logits: Tensor) -> Tensor:
    """PointRend's uncertainty of a mask logit: highest where the logit is nearest 0."""
    return -logits.abs()


def most_uncertain_cells(logits: Tensor, count: int) -> tuple[Tensor, Tensor]:
    """The ``count`` most uncertain cells of (R, H, W) logits: flat indices (R, k) and centres (R, k, 2)."""
    rows, height, width = logits.shape
    count = min(count, height * width)
    index = torch.topk(uncertainty(logits).view(rows, -1), k=count, dim=1).indices
    x = ((index % width).float() + 0.5) / width
    y = (torch.div(index, width, rounding_mode="floor").float() + 0.5) / height
    return index, torch.stack([x, y], dim=2)


class CoarseMaskHead(nn.Module):
    """Regular-grid features (R, C, S, S) -> coarse logits (R, K, r, r): 2x2/2 conv, FCs, a linear layer."""

    def __init__(self, channels: int, num_classes: int, cfg: PointRendSettings):
        super().__init__()
        if channels > cfg.conv_dim:  # detectron2 would put a 1x1 reduction conv first: another layout
            raise ValueError(f"PointRend's coarse head needs conv_dim >= the {channels} feature channels")
        self.num_classes = num_classes
        self.resolution = cfg.coarse_resolution
        self.conv = nn.Conv2d(channels, cfg.conv_dim, kernel_size=2, stride=2)
        dims = [cfg.conv_dim * (cfg.pooler_resolution // 2) ** 2] + [cfg.fc_dim] * cfg.num_fc
        self.fcs = nn.ModuleList(nn.Linear(a, b) for a, b in zip(dims[:-1], dims[1:], strict=True))
        self.predictor = nn.Linear(dims[-1], num_classes * self.resolution**2)
        nn.init.kaiming_normal_(self.conv.weight, mode="fan_out", nonlinearity="relu")
        nn.init.zeros_(self.conv.bias)
        for fc in self.fcs:
            nn.init.kaiming_uniform_(fc.weight, a=1)
            nn.init.zeros_(fc.bias)
        nn.init.normal_(self.predictor.weight, std=0.001)
        nn.init.zeros_(self.predictor.bias)

    def forward(self, x: Tensor) -> Tensor:
        x = F.relu(self.conv(x)).flatten(1)
        for fc in self.fcs:
            x = F.relu(fc(x))
        return self.predictor(x).view(len(x), self.num_classes, self.resolution, self.resolution)


class PointHead(nn.Module):
    """Per-point MLP over [fine feature, coarse logits]; the coarse logits join every layer's input."""

    def __init__(self, channels: int, num_classes: int, cfg: PointRendSettings):
        super().__init__()
        dims = [channels] + [cfg.point_fc_dim] * cfg.point_num_fc
        self.fcs = nn.ModuleList(
            nn.Conv1d(a + num_classes, b, kernel_size=1) for a, b in zip(dims[:-1], dims[1:], strict=True)
        )
        self.predictor = nn.Conv1d(dims[-1] + num_classes, num_classes, kernel_size=1)
        for fc in self.fcs:
            nn.init.kaiming_normal_(fc.weight, mode="fan_out", nonlinearity="relu")
            nn.init.zeros_(fc.bias)
        nn.init.normal_(self.predictor.weight, std=0.001)
        nn.init.zeros_(self.predictor.bias)

    def forward(self, fine: Tensor, coarse: Tensor, classes: Tensor | None = None) -> Tensor:
        """Logits (R, K, P) for every class, or (R, P) for each row's class in ``classes``.

        The 1-wide convs run as matrix products over (R * P, C) rows (a quarter faster on CPUs).
        Predicting one class per row is the same arithmetic as picking it from all K, at 1/K the cost.
        """
        rows, _, count = fine.shape
        x = fine.transpose(1, 2).reshape(rows * count, -1)
        c = coarse.transpose(1, 2).reshape(rows * count, -1)
        for fc in self.fcs:
            x = F.relu(F.linear(torch.cat([x, c], dim=1), fc.weight[:, :, 0], fc.bias))
        x = torch.cat([x, c], dim=1).view(rows, count, -1)
        if classes is None:
            return F.linear(x, self.predictor.weight[:, :, 0], self.predictor.bias).transpose(1, 2)
        weight = self.predictor.weight[classes, :, 0]  # (R, D)
        return torch.einsum("rpd,rd->rp", x, weight) + self.predictor.bias[classes, None]


class PointRendMaskHead(nn.Module):
    """Coarse head + point head on one feature map; see the module docstring."""

    def __init__(self, channels: int, stride: int, num_classes: int, cfg: PointRendSettings):
        super().__init__()
        self.cfg = cfg
        self.stride = stride
        self.coarse_head = CoarseMaskHead(channels, num_classes, cfg)
        self.point_head = PointHead(channels, num_classes, cfg)
        # Steps whose points would cover the whole upsampled grid are a denser starting grid instead.
        self.start_resolution, self.steps = cfg.coarse_resolution, cfg.subdivision_steps
        while 4 * self.start_resolution**2 <= cfg.subdivision_num_points:
            self.start_resolution *= 2
            self.steps -= 1

    @property
    def output_resolution(self) -> int:
        return self.start_resolution * 2 ** max(self.steps, 0)

    def coarse_logits(self, feature: Tensor, boxes: list[Tensor]) -> Tensor:
        side = self.cfg.pooler_resolution
        points = regular_grid(side, sum(len(b) for b in boxes), feature.device)
        pooled = sample_box_points(feature, self.stride, boxes, points)
        return self.coarse_head(pooled.view(len(pooled), feature.shape[1], side, side))

    def point_logits(
        self, feature: Tensor, boxes: list[Tensor], coarse: Tensor, points: Tensor, classes: Tensor | None = None
    ) -> Tensor:
        fine = sample_box_points(feature, self.stride, boxes, points)
        return self.point_head(fine, point_sample(coarse, points), classes)

    @torch.no_grad()
    def predict(self, features: Mapping[str, Tensor], boxes: list[Tensor], classes: Tensor) -> Tensor:
        """Mask logits (R, M, M) of each box's class by adaptive subdivision (M = ``output_resolution``)."""
        feature = features[self.cfg.in_feature]
        if not len(classes):
            return feature.new_zeros((0, self.output_resolution, self.output_resolution))
        coarse = self.coarse_logits(feature, boxes)
        side = self.start_resolution
        points = regular_grid(side, len(classes), feature.device)
        logits = self.point_logits(feature, boxes, coarse, points, classes).view(len(classes), side, side)
        for _ in range(self.steps):
            logits = F.interpolate(logits[:, None], scale_factor=2, mode="bilinear", align_corners=False)[:, 0]
            index, points = most_uncertain_cells(logits, self.cfg.subdivision_num_points)
            refined = self.point_logits(feature, boxes, coarse, points, classes)
            logits = logits.flatten(1).scatter(1, index, refined).view_as(logits)
        return logits

    def losses(
        self, features: Mapping[str, Tensor], proposals: list[Instances], targets: list[Instances]
    ) -> dict[str, Tensor]:
        """``loss_mask`` on the coarse logits and ``loss_mask_point`` on importance-sampled points.

        Points: ``oversample_ratio`` x ``train_num_points`` random candidates, the most uncertain
        ``importance_sample_ratio`` of them under the coarse prediction of the ground-truth class,
        the rest uniform; labels are the ground-truth masks sampled bilinearly at each point.
        """
        feature = features[self.cfg.in_feature]
        boxes = [p.proposal_boxes for p in proposals]
        coarse = self.coarse_logits(feature, boxes)
        classes = torch.cat([p.gt_classes for p in proposals])
        resolution = coarse.shape[-1]
        gt = batch_mask_targets([t.gt_masks for t in targets], [p.gt_index for p in proposals], boxes, resolution)
        loss = {"loss_mask": mask_rcnn_loss(coarse, classes, gt.to(coarse.dtype))}
        points = self._training_points(coarse, classes)
        labels = [
            bilinear_mask_values(t.gt_masks, p.gt_index, points_in_image(p.proposal_boxes, part))
            for p, t, part in zip(proposals, targets, points.split([len(b) for b in boxes]), strict=True)
            if len(p)
        ]
        logits = self.point_logits(feature, boxes, coarse, points, classes)
        if labels:
            loss["loss_mask_point"] = F.binary_cross_entropy_with_logits(logits, torch.cat(labels))
        else:
            loss["loss_mask_point"] = logits.sum() * 0.0
        return loss

    @torch.no_grad()
    def _training_points(self, coarse: Tensor, classes: Tensor) -> Tensor:
        cfg = self.cfg
        rows = len(classes)
        candidates = torch.rand(rows, cfg.train_num_points * cfg.oversample_ratio, 2, device=coarse.device)
        coarse_of_class = coarse[torch.arange(rows, device=coarse.device), classes][:, None]
        scores = uncertainty(point_sample(coarse_of_class, candidates)[:, 0])
        uncertain = int(cfg.importance_sample_ratio * cfg.train_num_points)
        index = torch.topk(scores, k=uncertain, dim=1).indices
        picked = torch.gather(candidates, 1, index[:, :, None].expand(-1, -1, 2))
        uniform = torch.rand(rows, cfg.train_num_points - uncertain, 2, device=coarse.device)
        return torch.cat([picked, uniform], dim=1)


def bilinear_mask_values(masks: Tensor, which: Tensor, points: Tensor) -> Tensor:
    """``grid_sample`` of bool masks (K, H, W) at image-pixel points (R, P, 2) of mask ``which[r]``: (R, P).

    Gathers the four neighbours directly instead of stacking a full-image copy of the mask per row.
    """
    height, width = masks.shape[1:]
    x = points[..., 0] - 0.5
    y = points[..., 1] - 0.5
    x0, y0 = x.floor(), y.floor()
    total = torch.zeros_like(x)
    for dx in (0, 1):
        for dy in (0, 1):
            xi, yi = x0 + dx, y0 + dy
            weight = (1 - (x - xi).abs()) * (1 - (y - yi).abs())
            inside = (xi >= 0) & (xi < width) & (yi >= 0) & (yi < height)
            xi = xi.clamp(0, width - 1).long()
            yi = yi.clamp(0, height - 1).long()
            values = masks[which[:, None].expand_as(xi), yi, xi]
            total = total + torch.where(inside & values, weight, torch.zeros_like(weight))
    return total
