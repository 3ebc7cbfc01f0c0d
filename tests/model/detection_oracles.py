"""Plain-loop reference implementations used as oracles by the op tests.

They transcribe the published semantics (torchvision's RoIAlign CPU kernel and the
textbook greedy NMS) one sample / one box at a time, sharing no code with usl; and the RoI
heads' former proposal sampling, which read each image's label counts from the device.
"""

from __future__ import annotations

import math

import torch


def _bilinear(feature, y: float, x: float) -> torch.Tensor:
    """torchvision's bilinear_interpolate on a (C, H, W) map."""
    height, width = feature.shape[1:]
    if y < -1.0 or y > height or x < -1.0 or x > width:
        return feature.new_zeros(feature.shape[0])
    y, x = max(y, 0.0), max(x, 0.0)
    y_low, x_low = int(y), int(x)
    if y_low >= height - 1:
        y_high = y_low = height - 1
        y = float(y_low)
    else:
        y_high = y_low + 1
    if x_low >= width - 1:
        x_high = x_low = width - 1
        x = float(x_low)
    else:
        x_high = x_low + 1
    ly, lx = y - y_low, x - x_low
    hy, hx = 1.0 - ly, 1.0 - lx
    return (
        hy * hx * feature[:, y_low, x_low]
        + hy * lx * feature[:, y_low, x_high]
        + ly * hx * feature[:, y_high, x_low]
        + ly * lx * feature[:, y_high, x_high]
    )


def roi_align_loop(features, rois, output_size, spatial_scale, sampling_ratio, aligned):
    """RoIAlign of (N, C, H, W) ``features`` over ``rois`` (K, 5), one sample at a time."""
    out_h, out_w = output_size
    outputs = []
    for roi in rois.tolist():
        feature = features[int(roi[0])]
        offset = 0.5 if aligned else 0.0
        x0, y0 = roi[1] * spatial_scale - offset, roi[2] * spatial_scale - offset
        x1, y1 = roi[3] * spatial_scale - offset, roi[4] * spatial_scale - offset
        roi_w, roi_h = x1 - x0, y1 - y0
        if not aligned:
            roi_w, roi_h = max(roi_w, 1.0), max(roi_h, 1.0)
        bin_h, bin_w = roi_h / out_h, roi_w / out_w
        grid_h = sampling_ratio if sampling_ratio > 0 else math.ceil(roi_h / out_h)
        grid_w = sampling_ratio if sampling_ratio > 0 else math.ceil(roi_w / out_w)
        count = max(grid_h * grid_w, 1)
        pooled = features.new_zeros(features.shape[1], out_h, out_w)
        for ph in range(out_h):
            for pw in range(out_w):
                total = features.new_zeros(features.shape[1])
                for iy in range(grid_h):
                    y = y0 + ph * bin_h + (iy + 0.5) * bin_h / grid_h
                    for ix in range(grid_w):
                        x = x0 + pw * bin_w + (ix + 0.5) * bin_w / grid_w
                        total = total + _bilinear(feature, y, x)
                pooled[:, ph, pw] = total / count
        outputs.append(pooled)
    return torch.stack(outputs) if outputs else features.new_zeros(0, features.shape[1], out_h, out_w)


def iou_single(a, b) -> float:
    """IoU of two [x0, y0, x1, y1] boxes given as lists."""
    iw = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    ih = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = iw * ih
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter
    return inter / union if union > 0 else float("nan")


def nms_loop(boxes, scores, iou_threshold, groups=None):
    """Greedy NMS: highest score first (ties: lower index first), drop IoU > threshold in the same group."""
    boxes, scores = boxes.tolist(), scores.tolist()
    groups = [0] * len(boxes) if groups is None else groups.tolist()
    order = sorted(range(len(boxes)), key=lambda i: (-scores[i], i))
    keep = []
    for i in order:
        if all(groups[i] != groups[k] or not iou_single(boxes[i], boxes[k]) > iou_threshold for k in keep):
            keep.append(i)
    return keep


def torchvision_ops():
    """torchvision.ops if it imports *and* its compiled kernels run here, else None."""
    try:
        import torchvision.ops as ops

        ops.nms(torch.zeros(1, 4), torch.zeros(1), 0.5)
        return ops
    except Exception:  # ImportError, or a broken compiled extension (RuntimeError, OSError, ...)
        return None


def subsample_labels_read_per_image(
    labels: torch.Tensor, num_samples: int, positive_fraction: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """The former ``subsample_labels``: its two ``nonzero`` read each image's counts from the device."""
    positive = torch.nonzero(labels == 1).squeeze(1)
    negative = torch.nonzero(labels == 0).squeeze(1)
    num_positive = min(positive.numel(), int(num_samples * positive_fraction))
    num_negative = min(negative.numel(), num_samples - num_positive)
    positive = positive[torch.randperm(positive.numel(), device=labels.device)[:num_positive]]
    negative = negative[torch.randperm(negative.numel(), device=labels.device)[:num_negative]]
    return positive, negative
