"""Detection operators in pure torch: RoIAlign, NMS, box maths and anchors."""

from .anchors import AnchorGenerator, cell_anchors
from .autocast import autocast_off
from .boxes import (
    DEFAULT_SCALE_CLAMP,
    Box2BoxTransform,
    box_area,
    box_iou,
    clip_boxes,
    nonempty_boxes,
    padded_match_quality,
    pairwise_intersection,
    stack_padded,
)
from .nms import batched_nms, kept_by_image, nms
from .roi_align import RoIAlign, convert_boxes_to_rois, roi_align, roi_align_levels

__all__ = [
    "AnchorGenerator",
    "Box2BoxTransform",
    "DEFAULT_SCALE_CLAMP",
    "RoIAlign",
    "autocast_off",
    "batched_nms",
    "box_area",
    "box_iou",
    "cell_anchors",
    "clip_boxes",
    "convert_boxes_to_rois",
    "kept_by_image",
    "nms",
    "nonempty_boxes",
    "pairwise_intersection",
    "roi_align",
    "roi_align_levels",
    "padded_match_quality",
    "stack_padded",
]
