"""The paper's 2D silhouette losses (Sec. 3.4): l_dist, l_xent and l_2D = l_dist + 1[IoU > 0.5] l_xent.

All functions work on a batch of P (object, view) pairs at once.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F

from usl.geometry.cameras import project
from usl.geometry.nearest import DEFAULT_MAX_ELEMENTS, chamfer_directions, lengths_to_mask
from usl.utils.transfer import constant, to_device

Tensor = torch.Tensor

# Projected mesh points closer to the camera than this (homogeneous depth, metres for an
# upper-triangular K) are dropped: behind the camera they have no image, and just in front
# of it they land arbitrarily far away and would swamp the loss.
DEFAULT_MIN_DEPTH = 1e-2
# Mask coverage this close to 0 or 1 counts as exactly 0 or 1 in the l_xent diagnostics: far above
# the rounding of ``usl.render.resample``'s float64 summed-area differences, far below a pixel's share.
COVERAGE_ROUNDING = 1e-9


def sample_mask_points(
    masks: Tensor,
    num_points: int,
    boxes: Tensor | None = None,
    jitter: bool = True,
    generator: torch.Generator | None = None,
) -> tuple[Tensor, Tensor]:
    """Sample up to ``num_points`` distinct pixels uniformly from each binary mask.

    A mask with fewer foreground pixels than ``num_points`` gives all of them. Batched:
    one random key per pixel and a top-k, no loop over masks.

    Args:
        masks: (P, H, W) bool (or values > 0.5 count as foreground), dense images or crops.
        boxes: optional (P, 4) xyxy image-frame boxes the mask grids span (for crops).
            Without boxes, mask pixel (r, c) is the image pixel [c, c+1] x [r, r+1].
        jitter: place each point uniformly inside its pixel instead of at the pixel centre.
        generator: torch.Generator on the masks' device, for reproducible draws.
    Returns:
        points: (P, num_points, 2) (u, v) in the image pixel frame of docs/design.md §2;
            the first ``lengths[p]`` rows are samples, the rest zero padding.
        lengths: (P,) int64 number of samples per mask.
    """
    if masks.dim() != 3:
        raise ValueError(f"sample_mask_points: masks must be (P, H, W), got {tuple(masks.shape)}")
    num_masks, height, width = masks.shape
    device = masks.device
    flat = (masks > 0.5 if masks.is_floating_point() else masks.bool()).reshape(num_masks, height * width)
    k = min(num_points, height * width)
    keys = torch.rand(flat.shape, device=device, generator=generator).masked_fill(~flat, -1.0)
    top, idx = keys.topk(k, dim=1)
    lengths = (top >= 0).sum(dim=1)
    if jitter:
        offsets = torch.rand(num_masks, k, 2, device=device, generator=generator)
    else:
        offsets = torch.full((num_masks, k, 2), 0.5, device=device)
    points = torch.stack([idx % width, idx // width], dim=-1) + offsets
    if boxes is not None:
        scale = (boxes[:, 2:] - boxes[:, :2]) / constant((width, height), boxes.dtype, device)
        points = boxes[:, None, :2] + points * scale[:, None, :]
    points = torch.where(lengths_to_mask(lengths, k).unsqueeze(-1), points, 0.0)
    if k < num_points:
        points = F.pad(points, (0, 0, 0, num_points - k))
    return points, lengths


def _image_scale(image_size: Tensor | tuple[int, int], num_pairs: int, like: Tensor) -> Tensor:
    """(P,) 1 / max(H, W) per pair."""
    if isinstance(image_size, Tensor):
        size = image_size.to(device=like.device, dtype=like.dtype)
    else:
        size = to_device(image_size, like.device, like.dtype)
    if size.dim() == 1:
        size = size.expand(num_pairs, 2)
    return 1.0 / size.max(dim=-1).values


def silhouette_chamfer_loss(
    points_cam: Tensor,
    K: Tensor,
    image_size: Tensor | tuple[int, int],
    true_points: Tensor,
    true_lengths: Tensor | None = None,
    min_depth: float = DEFAULT_MIN_DEPTH,
    max_elements: int = DEFAULT_MAX_ELEMENTS,
) -> Tensor:
    """l_dist: bidirectional 2D Chamfer between the projected mesh and the true silhouette.

    Approximates the paper's Eq. (3) without rendering: ``points_cam`` are points sampled
    on the mesh surface (``sample_points_from_meshes``) and moved into view j's camera
    frame; they are projected with view j's K (``cameras.project``). Each direction is the
    mean squared distance to the nearest point of the other set; the loss is their sum.

    Unit: pixel coordinates divided by max(H, W) of the pair's view, so the loss does not
    depend on image resolution (a displacement across the whole long side is 1).

    Args:
        points_cam: (P, N, 3) mesh surface points in view j's camera frame.
        K: (P, 3, 3) (or broadcastable) intrinsics of view j.
        image_size: (P, 2) or a shared (H, W) of view j.
        true_points: (P, M, 2) silhouette points in view j's pixel frame (``sample_mask_points``).
        true_lengths: (P,) valid rows of ``true_points``; all M valid if None.
        min_depth: mesh points with homogeneous depth below this are excluded.
    Returns:
        (P,) per-pair loss, differentiable w.r.t. ``points_cam`` (and K). A pair with no
        projected point in front of the camera, or an empty true silhouette, gets 0 and
        no gradient; callers should drop pairs with empty true silhouettes.
    """
    num_pairs = points_cam.shape[0]
    uv, depth = project(points_cam, K)
    pred_valid = depth > min_depth
    scale = _image_scale(image_size, num_pairs, uv)[:, None, None]
    if true_lengths is None:
        true_valid = torch.ones(true_points.shape[:2], dtype=torch.bool, device=true_points.device)
    else:
        true_valid = lengths_to_mask(true_lengths, true_points.shape[1])
    # a few hundred points a side: exact brute force as a compiled loop on the CPU
    pred_to_true, true_to_pred = chamfer_directions(
        uv * scale, true_points.to(uv.dtype) * scale, pred_valid, true_valid, max_elements, backend="loop"
    )
    pred_count = pred_valid.sum(dim=1).clamp(min=1)
    true_count = true_valid.sum(dim=1).clamp(min=1)
    return pred_to_true.sum(dim=1) / pred_count + true_to_pred.sum(dim=1) / true_count


class SilhouetteBCE(NamedTuple):
    """Per-pair l_xent, and the IoU gate of l_2D (neither gate nor IoU carries gradient)."""

    loss: Tensor  # (P,) mean per-pixel binary cross-entropy, NOT gated
    gate: Tensor  # (P,) bool, IoU(soft > 0.5, true) > iou_threshold
    iou: Tensor  # (P,) that IoU (0 where both masks are empty)
    # Diagnostics (no gradient). BCE clamps log(0) at -100, so a true pixel that no face reaches
    # (soft exactly 0) costs a constant 100 with zero gradient; a handful of them dominate the
    # mean. ``loss_reached`` is the mean over the other cells, ``unreached`` the fraction of
    # true-foreground cells no face reaches.
    loss_reached: Tensor  # (P,)
    unreached: Tensor  # (P,)


def silhouette_bce_loss(
    soft: Tensor, true: Tensor, valid: Tensor | None = None, iou_threshold: float = 0.5
) -> SilhouetteBCE:
    """l_xent between soft silhouettes (P, R, R) in [0, 1] and the matching true-mask crops.

    ``soft`` comes from the dynamic renderer (``usl.render.render_dynamic(...).soft``) and
    ``true`` is the true mask over the same window: bool, {0, 1}, or fractional coverage in
    [0, 1] (``DynamicRender.target``); the IoU counts coverage > 0.5 as foreground.
    ``valid`` (P, R, R) bool restricts both the mean and the IoU to observed cells
    (``DynamicRender.valid``: cells inside the image). The gate is computed without
    gradient, as the paper's indicator 1[IoU > 0.5].
    """
    if soft.shape != true.shape or (valid is not None and valid.shape != soft.shape):
        shapes = [tuple(t.shape) for t in (soft, true) + (() if valid is None else (valid,))]
        raise ValueError(f"silhouette_bce_loss: soft, true (and valid) must have one shape, got {shapes}")
    target = true.to(soft.dtype)
    cells = torch.ones_like(soft, dtype=torch.bool) if valid is None else valid.bool()
    per_cell = F.binary_cross_entropy(soft, target, reduction="none")
    weight = cells.to(soft.dtype).flatten(1)
    loss = (per_cell.flatten(1) * weight).sum(1) / weight.sum(1).clamp(min=1)
    with torch.no_grad():
        pred_fg = (soft > 0.5).flatten(1) & cells.flatten(1)
        true_fg = (target > 0.5).flatten(1) & cells.flatten(1)
        inter = (pred_fg & true_fg).sum(dim=1)
        union = (pred_fg | true_fg).sum(dim=1)
        iou = torch.where(union > 0, inter / union.clamp(min=1), 0.0).to(soft.dtype)
        # coverage within COVERAGE_ROUNDING of 0 or 1 is the summed-area table's float64 rounding
        # (~1e-14, depending on the CPU's vector unit), not a mask pixel: it costs nothing clamped
        clamped = ((soft == 0) & (target > COVERAGE_ROUNDING)) | ((soft == 1) & (target < 1 - COVERAGE_ROUNDING))
        kept = weight * (~clamped).flatten(1)
        loss_reached = (per_cell.flatten(1) * kept).sum(1) / kept.sum(1).clamp(min=1)
        true_cells = target.flatten(1) * weight
        unreached = (true_cells * (soft == 0).flatten(1)).sum(1) / true_cells.sum(1).clamp(min=1e-6)
    return SilhouetteBCE(loss, iou > iou_threshold, iou, loss_reached, unreached)


def soft_iou_loss(soft: Tensor, true: Tensor, valid: Tensor | None = None) -> Tensor:
    """(P,) 1 - soft IoU between soft silhouettes (P, R, R) and the matching true-mask crops over the
    ``valid`` cells (SoftRas's silhouette loss). Each pair is normalised by its own union, so an
    object's thin parts weigh as much as a large object's; 1, with no gradient, where both are empty."""
    target = true.to(soft.dtype).flatten(1)
    pred = soft.flatten(1)
    weight = torch.ones_like(pred) if valid is None else valid.flatten(1).to(soft.dtype)
    inter = (pred * target * weight).sum(1)
    union = ((pred + target - pred * target) * weight).sum(1)
    return 1.0 - inter / union.clamp(min=1e-6)


def l2d_loss(dist: Tensor, xent: SilhouetteBCE) -> Tensor:
    """Per-pair l_2D = l_dist + 1[IoU > 0.5] * l_xent (paper Eq. 4).

    The paper's L_3D is the mean of this over objects and views: ``l2d_loss(...).mean()``
    over the P pairs of a batch (after dropping pairs without a true silhouette).
    """
    return dist + torch.where(xent.gate, xent.loss, torch.zeros_like(xent.loss))
