"""Dynamic rendering (paper Sec. 3.4): rasterize only around the object, at a fixed resolution.

For each (object, view) pair p the window is chosen as follows (all in view p's pixel frame):

1. union of the true silhouette's box and the box of the projected mesh (non-culled faces);
2. grown by ``padding`` times its longer side on every side, so the soft blur fringe fits;
3. intersected with the image: the true mask is unobserved outside the image, so mesh
   parts out there (truncated objects) are neither rendered nor penalised;
4. made square (side = the longer side, at least ``min_size`` pixels), keeping the box
   inside and shifted to lie inside the image whenever the side allows.

Square windows keep pixels isotropic, so ``sigma`` and ``blur_radius`` act equally in x
and y. A square can only leave the image when the box is wider than the image is tall
(or the reverse); ``valid`` then marks the cells whose centres lie inside the image. A
pair with neither a true silhouette nor a visible projected face gets a centred square
of the image's shorter side.

The mesh is rasterized at ``resolution`` x ``resolution`` through ``K_window = A @ K``,
where A maps the window onto the R x R grid, and the target is the exact-area coverage
of the true mask over each cell (:mod:`usl.render.resample`). Every step runs on all pairs at
once, on the device: the op count does not grow with the number of pairs, and no window is read
back to the host.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from usl.metrics.boxes import masks_to_boxes
from usl.render.masks import PaddedMasks
from usl.render.resample import resample_masks_area
from usl.render.screen import check_packed_inputs, project_faces
from usl.render.soft import SoftRasterSettings, rasterize_soft
from usl.utils.transfer import constant

Tensor = torch.Tensor


@dataclass
class DynamicRender:
    """Per (object, view) pair p: soft (P, R, R) differentiable silhouette; target (P, R, R)
    true-mask coverage in [0, 1]; valid (P, R, R) bool, cell centre inside the image;
    windows (P, 4) [x0, y0, x1, y1] in the image pixel frame; K_window (P, 3, 3)."""

    soft: Tensor
    target: Tensor
    valid: Tensor
    windows: Tensor
    K_window: Tensor


def render_dynamic(
    verts: Tensor,
    faces: Tensor,
    face_window: Tensor,
    K: Tensor,
    true_masks: PaddedMasks,
    resolution: int = 72,
    settings: SoftRasterSettings = SoftRasterSettings(),
    padding: float = 0.05,
    min_size: float = 4.0,
    true_boxes: Tensor | None = None,
    ignore_masks: Tensor | None = None,
) -> DynamicRender:
    """Soft silhouettes and matching true-mask crops for P (object, view) pairs.

    Args:
        verts: (V, 3) packed vertices, each mesh already in its view's camera frame
            (R_{1->j} applied).
        faces: (F, 3) long indices into ``verts``.
        face_window: (F,) long pair index p of each face, in [0, P).
        K: (P, 3, 3) full-image intrinsics of each pair's view.
        true_masks: each pair's true mask, at its view's image size (the windows stay inside
            that size, whatever the padding).
        resolution: R, the side of every rendered window (the paper: 128 or 72).
        settings: soft rasterizer parameters (the paper: the defaults).
        padding: growth of the union box, as a fraction of its longer side, on every side.
        min_size: smallest window side in image pixels.
        true_boxes: (P, 4) boxes of the true masks (e.g. the records' ``box_xyxy``), to skip
            computing them from the masks; they must contain the masks' True pixels.
        ignore_masks: optional (P, H, W) bool masks of unobserved pixels (e.g. where another object
            is in the way), padded as ``true_masks.padded``: cells covered more than half by them
            are not ``valid``.
    """
    check_packed_inputs(verts, faces, face_window, K, "render_dynamic")
    num_pairs = K.shape[0]
    if len(true_masks) != num_pairs:
        raise ValueError(f"render_dynamic: K has {num_pairs} pairs but true_masks has {len(true_masks)}")
    if ignore_masks is not None and ignore_masks.shape != true_masks.padded.shape:
        raise ValueError(
            f"render_dynamic: ignore_masks must be padded as true_masks, {tuple(true_masks.padded.shape)}; "
            f"got {tuple(ignore_masks.shape)}"
        )
    faces, face_window = faces.long(), face_window.long()
    image_sizes = true_masks.sizes.to(device=K.device, dtype=torch.float64)
    masks = true_masks.padded.to(K.device)
    with torch.no_grad():
        truth = mask_boxes(masks) if true_boxes is None else _empty_if_degenerate(true_boxes.to(torch.float64))
        boxes = _union(truth.to(K.device), projected_boxes(verts, faces, face_window, K, settings.near))
        windows = square_windows(boxes, image_sizes, padding, min_size)
    K_window = window_intrinsics(windows, resolution).to(K.dtype) @ K
    soft = rasterize_soft(verts, faces, face_window, K_window, resolution, resolution, settings)
    valid = _cells_inside_image(windows, image_sizes, resolution)
    if ignore_masks is None:
        target = resample_masks_area(masks, windows, resolution)
    else:  # both stacks in one call
        both = torch.cat([masks, ignore_masks.to(K.device)])
        target, hidden = resample_masks_area(both, windows.repeat(2, 1), resolution).split(num_pairs)
        valid = valid & (hidden <= 0.5)
    return DynamicRender(
        soft=soft,
        target=target.to(device=soft.device, dtype=soft.dtype),
        valid=valid,
        windows=windows.to(K.dtype),
        K_window=K_window,
    )


def mask_boxes(masks: Tensor) -> Tensor:
    """(P, 4) float64 pixel-frame boxes [x0, y0, x1, y1] of the masks' (P, H, W) True pixels.

    The tight box is the metrics' one (``usl.metrics.masks_to_boxes``); an empty mask gets the
    empty box (+inf, +inf, -inf, -inf) instead of NaN, because here boxes are united.
    """
    boxes = masks_to_boxes(masks).to(torch.float64)
    empty = boxes.isnan().any(dim=1, keepdim=True)
    return torch.where(empty, _empty_boxes(boxes.shape[0], boxes.device), boxes)


def _empty_boxes(count: int, device: torch.device) -> Tensor:
    inf = torch.inf
    return constant((inf, inf, -inf, -inf), torch.float64, device).expand(count, 4)


def _empty_if_degenerate(boxes: Tensor) -> Tensor:
    """Boxes without area (e.g. [0, 0, 0, 0] for an object absent from a view) become empty."""
    degenerate = (boxes[:, 2] <= boxes[:, 0]) | (boxes[:, 3] <= boxes[:, 1])
    return torch.where(degenerate[:, None], _empty_boxes(boxes.shape[0], boxes.device), boxes)


def projected_boxes(verts: Tensor, faces: Tensor, face_window: Tensor, K: Tensor, near: float) -> Tensor:
    """(P, 4) float64 boxes of each pair's projected non-culled faces (empty box if none)."""
    screen = project_faces(verts.detach(), faces, face_window, K.detach(), near)
    xy = screen.xy.to(torch.float64)  # (F, 3, 2)
    # culled faces bound nothing (masked, not dropped: dropping them reads their count from the device)
    visible = screen.visible[:, None]
    lo = torch.where(visible, xy.amin(dim=1), torch.inf)
    hi = torch.where(visible, xy.amax(dim=1), -torch.inf)
    boxes = _empty_boxes(K.shape[0], K.device).clone()
    boxes[:, :2] = boxes[:, :2].scatter_reduce(0, face_window[:, None].expand(-1, 2), lo, "amin")
    boxes[:, 2:] = boxes[:, 2:].scatter_reduce(0, face_window[:, None].expand(-1, 2), hi, "amax")
    return boxes


def _union(a: Tensor, b: Tensor) -> Tensor:
    return torch.cat([torch.minimum(a[:, :2], b[:, :2]), torch.maximum(a[:, 2:], b[:, 2:])], dim=1)


def square_windows(boxes: Tensor, image_sizes: Tensor, padding: float, min_size: float) -> Tensor:
    """Square windows (P, 4) around ``boxes``, clipped and shifted as the module docstring says.

    Args:
        boxes: (P, 4) float64 boxes, the empty box (+inf, +inf, -inf, -inf) allowed.
        image_sizes: (P, 2) float64 (height, width).
    """
    height, width = image_sizes[:, 0], image_sizes[:, 1]
    grow = padding * torch.maximum(boxes[:, 2] - boxes[:, 0], boxes[:, 3] - boxes[:, 1])
    grow = torch.where(torch.isfinite(grow), grow, torch.zeros_like(grow))  # empty boxes
    x0 = torch.maximum(boxes[:, 0] - grow, torch.zeros_like(width))
    y0 = torch.maximum(boxes[:, 1] - grow, torch.zeros_like(height))
    x1 = torch.minimum(boxes[:, 2] + grow, width)
    y1 = torch.minimum(boxes[:, 3] + grow, height)
    usable = (x1 > x0) & (y1 > y0)
    short = torch.minimum(height, width)
    x0 = torch.where(usable, x0, (width - short) / 2)
    x1 = torch.where(usable, x1, (width + short) / 2)
    y0 = torch.where(usable, y0, (height - short) / 2)
    y1 = torch.where(usable, y1, (height + short) / 2)
    side = torch.maximum(torch.maximum(x1 - x0, y1 - y0), torch.full_like(x0, min_size))
    left = _place(0.5 * (x0 + x1) - 0.5 * side, width - side)
    top = _place(0.5 * (y0 + y1) - 0.5 * side, height - side)
    return torch.stack([left, top, left + side, top + side], dim=1)


def _place(start: Tensor, slack: Tensor) -> Tensor:
    """Shift a window start into [min(0, slack), max(0, slack)]: inside the image if it fits,
    else covering the whole image extent along that axis."""
    return torch.clamp(
        start, torch.minimum(slack, torch.zeros_like(slack)), torch.maximum(slack, torch.zeros_like(slack))
    )


def window_intrinsics(windows: Tensor, resolution: int) -> Tensor:
    """(P, 3, 3) maps A taking image pixels to window pixels: u' = (u - x0) * R / (x1 - x0).

    With pixel centres at +0.5 this is a pure scale and shift of the pixel frame.
    """
    scale_x = resolution / (windows[:, 2] - windows[:, 0])
    scale_y = resolution / (windows[:, 3] - windows[:, 1])
    A = torch.zeros(windows.shape[0], 3, 3, dtype=windows.dtype, device=windows.device)
    A[:, 0, 0], A[:, 0, 2] = scale_x, -windows[:, 0] * scale_x
    A[:, 1, 1], A[:, 1, 2] = scale_y, -windows[:, 1] * scale_y
    A[:, 2, 2] = 1.0
    return A


def _cells_inside_image(windows: Tensor, image_sizes: Tensor, resolution: int) -> Tensor:
    centres = (torch.arange(resolution, dtype=windows.dtype, device=windows.device) + 0.5) / resolution
    xs = windows[:, 0:1] + centres * (windows[:, 2:3] - windows[:, 0:1])
    ys = windows[:, 1:2] + centres * (windows[:, 3:4] - windows[:, 1:2])
    inside_x = (xs >= 0) & (xs <= image_sizes[:, 1:2])
    inside_y = (ys >= 0) & (ys <= image_sizes[:, 0:1])
    return inside_y[:, :, None] & inside_x[:, None, :]
