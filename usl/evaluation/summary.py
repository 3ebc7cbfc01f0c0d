"""Dataset-level numbers from per-object rows: means over objects, per predictor.

Raw units are kept here (IoU and gIoU as fractions, depth in metres, Chamfer-L2 in m^2, F1 in
percent as Mesh R-CNN reports it); ``report`` scales them to each paper table's convention.
Undefined values (an object seen in no other view, a pair without true depth) are left out of
the mean, and how many objects each mean covers is reported next to it.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

METRICS = (
    "mask_iou_input",
    "mask_iou_views",
    "box_giou_input",
    "box_giou_views",
    "depth_l1_input",
    "depth_l1_views",
    "chamfer",
    "f1",
)


@dataclass
class DetectionCounts:
    """Detections vs. ground truth over the input views of a detecting predictor."""

    images: int = 0
    ground_truth: int = 0
    detections: int = 0
    matched: int = 0

    def add(self, ground_truth: int, detections: int, matched: int) -> None:
        self.images += 1
        self.ground_truth += ground_truth
        self.detections += detections
        self.matched += matched


@dataclass
class PredictorSummary:
    name: str
    predicts_layout: bool
    predicts_shape: bool
    uses_detections: bool
    num_objects: int = 0
    metrics: dict[str, float | None] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    detection: dict[str, float] = field(default_factory=dict)  # AP numbers and counts, detectors only
    # true category name -> {"num_objects", "metrics", "counts"}: the same means over that category's
    # objects (a mean over all objects hides which kind of shape a model fails on)
    categories: dict[str, dict[str, Any]] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return dict(self.__dict__)


def mean_over_objects(rows: Sequence[dict[str, Any]]) -> tuple[dict[str, float | None], dict[str, int]]:
    """Mean of each metric over the rows that define it (None when no row does) and those counts."""
    means: dict[str, float | None] = {}
    counts: dict[str, int] = {}
    for key in METRICS:
        values = [float(r[key]) for r in rows if key in r and r[key] is not None and math.isfinite(float(r[key]))]
        counts[key] = len(values)
        means[key] = sum(values) / len(values) if values else None
    return means, counts


def summarize(
    predictors: Sequence[Any],
    rows: Sequence[dict[str, Any]],
    detection_counts: dict[str, DetectionCounts],
    average_precision: dict[str, dict[str, float]],
) -> list[PredictorSummary]:
    """One summary per predictor, in the given order."""
    out = []
    for predictor in predictors:
        own = [r for r in rows if r["predictor"] == predictor.name]
        summary = PredictorSummary(
            predictor.name,
            bool(predictor.predicts_layout),
            bool(predictor.predicts_shape),
            bool(predictor.uses_detections),
            num_objects=len(own),
        )
        summary.metrics, summary.counts = mean_over_objects(own)
        for category in sorted({r["category"] for r in own if "category" in r}):
            members = [r for r in own if r.get("category") == category]
            means, counts = mean_over_objects(members)
            summary.categories[category] = {"num_objects": len(members), "metrics": means, "counts": counts}
        if predictor.uses_detections:
            counts = detection_counts.get(predictor.name, DetectionCounts())
            summary.detection = {**counts.__dict__, **average_precision.get(predictor.name, {})}
        out.append(summary)
    return out
