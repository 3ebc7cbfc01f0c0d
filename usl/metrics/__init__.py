"""Evaluation metrics of the paper (Sec. 4): 3D Chamfer / F1, mask IoU, box gIoU, nearest-depth L1."""

from usl.metrics.boxes import box_giou, masks_to_boxes
from usl.metrics.depth import depth_l1, nearest_depth
from usl.metrics.masks import mask_iou
from usl.metrics.shape3d import chamfer_f1, compare_meshes

__all__ = ["box_giou", "chamfer_f1", "compare_meshes", "depth_l1", "mask_iou", "masks_to_boxes", "nearest_depth"]
