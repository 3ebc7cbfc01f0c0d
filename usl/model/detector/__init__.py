"""Mask R-CNN (RPN, RoI box and mask heads) on top of :mod:`usl.model.backbone`."""

from .box_head import FastRCNNFCHead, FastRCNNOutputLayers
from .config import AnchorConfig, BoxHeadConfig, DetectorConfig, MaskHeadConfig, ROIHeadsConfig, RPNConfig
from .mask_head import (
    MaskRCNNConvUpsampleHead,
    batch_mask_targets,
    mask_rcnn_loss,
    mask_targets,
    paste_masks_in_image,
)
from .mask_rcnn import InvalidTargetError, MaskRCNN
from .matcher import Matcher, label_counts, subsample_labels, subsample_labels_dense
from .poolers import MultiScaleRoIAlign, assign_boxes_to_levels
from .roi_heads import ROI_HEADS, StandardROIHeads, build_roi_heads
from .rpn import RPN, RPNHead
from .structures import ImageList, Instances

__all__ = [
    "AnchorConfig",
    "BoxHeadConfig",
    "DetectorConfig",
    "FastRCNNFCHead",
    "FastRCNNOutputLayers",
    "ImageList",
    "Instances",
    "InvalidTargetError",
    "MaskHeadConfig",
    "MaskRCNN",
    "MaskRCNNConvUpsampleHead",
    "Matcher",
    "MultiScaleRoIAlign",
    "ROIHeadsConfig",
    "ROI_HEADS",
    "RPN",
    "RPNConfig",
    "RPNHead",
    "StandardROIHeads",
    "assign_boxes_to_levels",
    "build_roi_heads",
    "mask_rcnn_loss",
    "batch_mask_targets",
    "mask_targets",
    "paste_masks_in_image",
    "label_counts",
    "subsample_labels",
    "subsample_labels_dense",
]
