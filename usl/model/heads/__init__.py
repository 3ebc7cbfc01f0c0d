"""USL's heads on top of Mask R-CNN: layout (z, rho) and shape (ico-sphere refinement)."""

from .graph_conv import GraphConv
from .layout import LayoutHead, LayoutPrediction
from .shape import RefinementStage, ShapeHead, ShapePrediction
from .vertex_features import project_cube_to_image, roimap_features, vertalign_features

__all__ = [
    "GraphConv",
    "LayoutHead",
    "LayoutPrediction",
    "RefinementStage",
    "ShapeHead",
    "ShapePrediction",
    "project_cube_to_image",
    "roimap_features",
    "vertalign_features",
]
