"""Evaluation with the model's own detections: matching to ground truth, and COCO AP.

Matching (for the shape / layout metrics "w/ detections", paper Table 2 last row): detections are
visited in descending score and each takes the unmatched ground-truth instance of highest box IoU
if that IoU reaches ``iou_threshold`` (0.5), regardless of category. Matched detections are scored
like ground-truth-box predictions; unmatched ones only count in AP; missed instances are counted.

AP (bbox and segm) comes from pycocotools' COCOeval on COCO dicts built here: ground truth from the
input views' instances, detections with the predicted boxes (bbox) or the rendered meshes (segm; see
``usl.evaluation.render.detection_masks``: visible parts in the scene of the confident detections).
"""

from __future__ import annotations

import contextlib
import io
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from pycocotools.coco import COCO
from pycocotools.cocoeval import COCOeval

from usl.model.ops import box_iou
from usl.records import encode_mask, mask_bbox
from usl.records.coco import coco_annotation, xyxy_to_xywh

Tensor = torch.Tensor
IOU_TYPES = ("bbox", "segm")


def match_detections(
    boxes: Tensor, scores: Tensor, gt_boxes: Tensor, gt_ids: Tensor, iou_threshold: float = 0.5
) -> Tensor:
    """Greedy one-to-one matching by box IoU; returns the matched instance id of each detection (-1 if none)."""
    matched = torch.full((boxes.shape[0],), -1, dtype=torch.int64)
    if boxes.shape[0] == 0 or gt_boxes.shape[0] == 0:
        return matched
    iou = box_iou(boxes.float().cpu(), gt_boxes.float().cpu())
    free = torch.ones(gt_boxes.shape[0], dtype=torch.bool)
    for d in torch.argsort(scores.cpu(), descending=True, stable=True).tolist():
        candidates = torch.where(free, iou[d], torch.full_like(iou[d], -1.0))
        best = int(candidates.argmax())
        if candidates[best] >= iou_threshold:
            matched[d] = int(gt_ids[best])
            free[best] = False
    return matched


class CocoDetections:
    """Accumulates ground truth and detections image by image, then runs COCOeval."""

    def __init__(self, category_ids: Sequence[int], category_names: Sequence[str]):
        self.category_ids = list(category_ids)
        self.categories = [{"id": int(c), "name": n} for c, n in zip(category_ids, category_names, strict=True)]
        self.images: list[dict[str, Any]] = []
        self.gt: list[dict[str, Any]] = []
        self.dt: dict[str, list[dict[str, Any]]] = {t: [] for t in IOU_TYPES}

    def add_image(
        self,
        height: int,
        width: int,
        gt_labels: Tensor,
        gt_masks: Tensor,
        labels: Tensor,
        scores: Tensor,
        boxes: Tensor,
        masks: Tensor,
    ) -> None:
        """Ground truth (contiguous labels, (n, H, W) masks) and detections (labels, scores, xyxy boxes, (N, H, W) masks)."""
        image_id = len(self.images) + 1
        self.images.append({"id": image_id, "height": int(height), "width": int(width)})
        for label, mask in zip(gt_labels.tolist(), gt_masks.cpu().numpy(), strict=True):
            self.gt.append(
                coco_annotation(
                    len(self.gt) + 1, image_id, self.category_ids[label], encode_mask(mask), mask.sum(), mask_bbox(mask)
                )
            )
        for label, score, box, mask in zip(
            labels.tolist(), scores.tolist(), boxes.tolist(), masks.cpu().numpy(), strict=True
        ):
            common = {"image_id": image_id, "category_id": self.category_ids[label], "score": float(score)}
            self.dt["bbox"].append({**common, "bbox": xyxy_to_xywh(box)})
            self.dt["segm"].append({**common, "segmentation": encode_mask(mask)})

    def evaluate(self) -> dict[str, float]:
        """``{"bbox/AP", "bbox/AP50", "bbox/AP75", "segm/AP", ...}`` in percent (COCO's 0.5:0.95 AP)."""
        out: dict[str, float] = {}
        for iou_type in IOU_TYPES:
            stats = self._run(iou_type)
            for key, value in zip(("AP", "AP50", "AP75"), stats[:3], strict=True):
                out[f"{iou_type}/{key}"] = 100.0 * max(float(value), 0.0)
        return out

    def _run(self, iou_type: str) -> np.ndarray:
        if not self.dt[iou_type] or not self.gt:
            return np.zeros(3)
        quiet = io.StringIO()
        with contextlib.redirect_stdout(quiet):
            gt = COCO()
            gt.dataset = {"images": self.images, "annotations": self.gt, "categories": self.categories}
            gt.createIndex()
            dt = gt.loadRes([dict(d) for d in self.dt[iou_type]])
            evaluator = COCOeval(gt, dt, iou_type)
            evaluator.evaluate()
            evaluator.accumulate()
            evaluator.summarize()
        return evaluator.stats
