"""The paper's training losses: 2D silhouette losses (Sec. 3.4), shape regularizers, weighting,
and Mesh R-CNN's 3D mesh losses for the 3D-supervised baseline."""

from usl.losses.mesh3d import ChamferNormal, chamfer_normal_loss
from usl.losses.regularizers import (
    edge_length_per_mesh,
    laplacian_per_mesh,
    laplacian_smoothing_loss,
    mesh_edge_loss,
    normal_consistency,
    offset_l2_loss,
    offset_l2_per_mesh,
)
from usl.losses.schedule import PiecewiseLinear
from usl.losses.silhouette import (
    SilhouetteBCE,
    l2d_loss,
    sample_mask_points,
    silhouette_bce_loss,
    silhouette_chamfer_loss,
    soft_iou_loss,
)
from usl.losses.total import LossWeights, combine_losses

__all__ = [
    "ChamferNormal",
    "LossWeights",
    "PiecewiseLinear",
    "SilhouetteBCE",
    "chamfer_normal_loss",
    "combine_losses",
    "edge_length_per_mesh",
    "l2d_loss",
    "laplacian_per_mesh",
    "laplacian_smoothing_loss",
    "normal_consistency",
    "mesh_edge_loss",
    "offset_l2_loss",
    "offset_l2_per_mesh",
    "sample_mask_points",
    "silhouette_bce_loss",
    "silhouette_chamfer_loss",
    "soft_iou_loss",
]
