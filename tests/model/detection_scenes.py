"""A tiny synthetic detection set: coloured rectangles (class 0) and ellipses (class 1) on noise."""

from __future__ import annotations

import torch

from usl.model.ops import box_iou


def make_scene(generator: torch.Generator, size: int = 128, max_objects: int = 3, max_overlap: float = 0.2):
    """One normalised image (3, size, size) and its target dict {boxes, labels, masks}."""
    image = torch.rand(3, size, size, generator=generator) * 0.3
    centres = torch.arange(size, dtype=torch.float32) + 0.5
    ys, xs = torch.meshgrid(centres, centres, indexing="ij")
    boxes, labels, masks = [], [], []
    count = int(torch.randint(1, max_objects + 1, (1,), generator=generator))
    while len(boxes) < count:
        w, h = (torch.rand(2, generator=generator) * 40 + 20).tolist()
        x0 = round(float(torch.rand(1, generator=generator)) * (size - w))
        y0 = round(float(torch.rand(1, generator=generator)) * (size - h))
        box = torch.tensor([[x0, y0, x0 + w, y0 + h]])
        if boxes and box_iou(box, torch.tensor(boxes)).max() > max_overlap:
            continue  # keep objects mostly visible
        label = int(torch.randint(0, 2, (1,), generator=generator))
        if label == 0:
            mask = (xs >= x0) & (xs < x0 + w) & (ys >= y0) & (ys < y0 + h)
        else:
            mask = ((xs - x0 - w / 2) / (w / 2)) ** 2 + ((ys - y0 - h / 2) / (h / 2)) ** 2 <= 1
        image[:, mask] = (torch.rand(3, generator=generator) * 0.6 + 0.4)[:, None]
        masks = [m & ~mask for m in masks] + [mask]
        boxes.append(box[0].tolist())
        labels.append(label)
    masks = torch.stack(masks)
    tight = []
    for mask in masks:  # boxes around what stays visible
        rows, cols = torch.nonzero(mask, as_tuple=True)
        tight.append([cols.min(), rows.min(), cols.max() + 1, rows.max() + 1])
    target = {"boxes": torch.tensor(tight, dtype=torch.float32), "labels": torch.tensor(labels), "masks": masks}
    return (image - 0.4) / 0.3, target


def make_dataset(count: int, seed: int = 0, size: int = 128):
    generator = torch.Generator().manual_seed(seed)
    scenes = [make_scene(generator, size) for _ in range(count)]
    return torch.stack([image for image, _ in scenes]), [target for _, target in scenes]


def recall_and_mask_iou(outputs, targets, iou_threshold: float = 0.5) -> tuple[float, float]:
    """Share of objects found by a same-class detection with box IoU >= threshold, and the
    mean mask IoU of each object's best same-class detection (0 when there is none)."""
    found, mask_ious = 0, []
    for output, target in zip(outputs, targets, strict=True):
        for box, label, mask in zip(target["boxes"], target["labels"], target["masks"], strict=True):
            same = output["labels"] == label
            if not same.any():
                mask_ious.append(0.0)
                continue
            ious = box_iou(box[None], output["boxes"][same])[0]
            best = int(ious.argmax())
            found += int(ious[best] >= iou_threshold)
            predicted = output["masks"][same][best]
            mask_ious.append(float((predicted & mask).sum() / (predicted | mask).sum()))
    return found / len(mask_ious), sum(mask_ious) / len(mask_ious)
