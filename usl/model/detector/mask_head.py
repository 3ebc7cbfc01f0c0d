"""Mask R-CNN mask branch: conv head, training targets/loss, and pasting masks into images."""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import nn

from ..ops import roi_align

Tensor = torch.Tensor

# Grid elements (masks x pixels) sampled at once when pasting masks into images.
_PASTE_CHUNK_ELEMENTS = 1 << 24


class MaskRCNNConvUpsampleHead(nn.Module):
    """``num_conv`` 3x3 convs, a 2x deconv, then one mask logit map per class: (R, C, 2S, 2S)."""

    def __init__(self, in_channels: int, num_classes: int, num_conv: int, conv_dim: int):
        super().__init__()
        dims = [in_channels] + [conv_dim] * num_conv
        self.convs = nn.ModuleList(nn.Conv2d(a, b, 3, padding=1) for a, b in zip(dims[:-1], dims[1:], strict=True))
        self.deconv = nn.ConvTranspose2d(dims[-1], conv_dim, kernel_size=2, stride=2)
        self.predictor = nn.Conv2d(conv_dim, num_classes, 1)
        for layer in [*self.convs, self.deconv]:
            nn.init.kaiming_normal_(layer.weight, mode="fan_out", nonlinearity="relu")
            nn.init.zeros_(layer.bias)
        nn.init.normal_(self.predictor.weight, std=0.001)
        nn.init.zeros_(self.predictor.bias)

    def forward(self, x: Tensor) -> Tensor:
        for conv in self.convs:
            x = F.relu(conv(x))
        return self.predictor(F.relu(self.deconv(x)))


def mask_targets(gt_masks: Tensor, gt_index: Tensor, boxes: Tensor, resolution: int) -> Tensor:
    """Crop each matched ground-truth mask to its proposal box and resize: (P, M, M) bool.

    ``gt_masks`` (K, H, W) of one image, ``gt_index`` (P,) the matched mask per box. Uses
    aligned RoIAlign on the binary mask and a 0.5 threshold, so targets agree with how
    features are pooled for the same box.
    """
    rois = torch.cat([gt_index[:, None].to(boxes.dtype), boxes], dim=1)
    crops = roi_align(gt_masks[:, None], rois, resolution, spatial_scale=1.0, sampling_ratio=0, aligned=True)
    return crops[:, 0] >= 0.5


def batch_mask_targets(
    gt_masks: Sequence[Tensor], gt_index: Sequence[Tensor], boxes: Sequence[Tensor], resolution: int
) -> Tensor:
    """:func:`mask_targets` of several images, rows image after image: one RoIAlign (one host read)
    per distinct mask size instead of one per image, each image's masks stacked with its ``gt_index``
    offset into the stack."""
    groups: dict[tuple[int, ...], list[int]] = {}
    for image, masks in enumerate(gt_masks):
        if len(boxes[image]):
            groups.setdefault(tuple(masks.shape[-2:]), []).append(image)
    crops = {}
    for images in groups.values():
        offsets = [0]
        for image in images[:-1]:
            offsets.append(offsets[-1] + len(gt_masks[image]))
        stacked = mask_targets(
            torch.cat([gt_masks[image] for image in images]),
            torch.cat([gt_index[image] + offset for image, offset in zip(images, offsets, strict=True)]),
            torch.cat([boxes[image] for image in images]),
            resolution,
        )
        crops.update(zip(images, stacked.split([len(boxes[image]) for image in images]), strict=True))
    if not crops:
        return torch.zeros((0, resolution, resolution), dtype=torch.bool, device=gt_masks[0].device)
    return torch.cat([crops[image] for image in sorted(crops)])


def mask_rcnn_loss(mask_logits: Tensor, classes: Tensor, targets: Tensor) -> Tensor:
    """Mean per-pixel binary cross-entropy of each RoI's mask for its ground-truth class."""
    if mask_logits.shape[0] == 0:
        return mask_logits.sum() * 0.0
    picked = mask_logits[torch.arange(len(classes), device=classes.device), classes]
    return F.binary_cross_entropy_with_logits(picked, targets.to(picked.dtype))


def select_class_masks(mask_logits: Tensor, classes: Tensor) -> Tensor:
    """Probabilities (R, M, M) of each RoI's mask for its predicted class."""
    picked = mask_logits[torch.arange(len(classes), device=classes.device), classes]
    return picked.sigmoid()


def paste_masks_in_image(
    masks: Tensor, boxes: Tensor, image_size: tuple[int, int], threshold: float | None = 0.5
) -> Tensor:
    """Resample box-relative masks (R, M, M) into full images (R, H, W).

    Pixel ``(x, y)`` has its centre at ``(x + 0.5, y + 0.5)`` (docs/design.md §2); the mask's
    M x M cells tile the box exactly, matching how :func:`mask_targets` cut them.
    Returns probabilities, or bool masks (``>= threshold``) when a threshold is given.
    """
    height, width = image_size
    chunk = max(1, _PASTE_CHUNK_ELEMENTS // max(2 * height * width, 1))
    xs = torch.arange(width, device=masks.device, dtype=torch.float32) + 0.5
    ys = torch.arange(height, device=masks.device, dtype=torch.float32) + 0.5
    pasted = []
    for part_masks, part_boxes in zip(masks.split(chunk), boxes.float().split(chunk), strict=True):
        x0, y0, x1, y1 = part_boxes.unbind(dim=1)
        grid_x = (xs[None] - x0[:, None]) / (x1 - x0).clamp(min=1e-6)[:, None] * 2 - 1
        grid_y = (ys[None] - y0[:, None]) / (y1 - y0).clamp(min=1e-6)[:, None] * 2 - 1
        grid = torch.stack([grid_x[:, None, :].expand(-1, height, -1), grid_y[:, :, None].expand(-1, -1, width)], dim=3)
        image = F.grid_sample(part_masks[:, None].float(), grid, mode="bilinear", align_corners=False)[:, 0]
        pasted.append(image if threshold is None else image >= threshold)
    if not pasted:
        dtype = torch.float32 if threshold is None else torch.bool
        return torch.zeros((0, height, width), dtype=dtype, device=masks.device)
    return torch.cat(pasted)
