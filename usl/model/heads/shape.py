"""Shape head (paper Sec. 3.3): an identical ico-sphere per object, deformed in the normalized cube.

Each of S refinement stages samples a feature per vertex (RoIMap, or RoIAlign + VertAlign for
the ablation), projects it to ``hidden_dim`` (Mesh R-CNN's bottleneck), runs ``num_graph_convs``
GraphConvs on [features, positions] and predicts offsets with a Linear on [features, positions]:
``dV_i = tanh(offset)``, ``V_i = V_{i-1} + dV_i``. As the paper states, V_0 (the unit sphere) and
each dV_i lie in [-1, 1]; V itself is not clamped (a clamp would stop the gradient of any vertex
that touches the cube's faces), and the frustum map guards points beyond the far plane
(``usl.geometry.frustum``). The pre-tanh offsets are kept for the ½‖dV‖² regularizer.
``category_templates`` (an option, off in the paper's recipes) starts each object from its
category's learned mean shape ``V_0 = sphere + T_c`` instead of the bare sphere.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import torch
from torch import nn

from usl.config import ShapeHeadConfig
from usl.geometry import ico_sphere, unique_edges

from .graph_conv import GraphConv
from .vertex_features import roimap_features, single_level_pooler, vertalign_features

Tensor = torch.Tensor


@dataclass
class ShapePrediction:
    verts: Tensor  # (N, V, 3) final vertices V_S in the normalized cube
    stage_verts: list[Tensor]  # V_1 .. V_S, each (N, V, 3)
    offsets: list[Tensor]  # pre-tanh offsets of each stage, (N, V, 3)


class RefinementStage(nn.Module):
    """One {vertex features, GraphConvs, offsets} stage."""

    def __init__(self, feature_dim: int, hidden_dim: int, num_graph_convs: int, graph_conv_init: str = "normal"):
        super().__init__()
        self.bottleneck = nn.Linear(feature_dim, hidden_dim)
        self.gconvs = nn.ModuleList(
            GraphConv(hidden_dim + 3, hidden_dim, graph_conv_init) for _ in range(num_graph_convs)
        )
        self.offset = nn.Linear(hidden_dim + 3, 3)
        nn.init.zeros_(self.offset.weight)  # start from the sphere (Mesh R-CNN's init)
        nn.init.zeros_(self.offset.bias)

    def forward(self, verts: Tensor, vertex_features: Tensor, edges: Tensor) -> Tensor:
        """Pre-tanh offsets (N, V, 3)."""
        positions = verts.to(vertex_features.dtype)
        x = torch.relu(self.bottleneck(vertex_features))
        for gconv in self.gconvs:
            x = torch.relu(gconv(torch.cat([x, positions], dim=-1), edges))
        return self.offset(torch.cat([x, positions], dim=-1))


class ShapeHead(nn.Module):
    """``num_classes`` sizes the per-category templates (``cfg.category_templates``)."""

    def __init__(self, feature_channels: int, feature_stride: int, cfg: ShapeHeadConfig, num_classes: int = 1):
        super().__init__()
        self.cfg = cfg
        self.stride = feature_stride
        verts, faces = ico_sphere(cfg.ico_level)
        self.register_buffer("sphere_verts", verts, persistent=False)
        # zeros: every template starts as the sphere, so a fresh head is the paper's
        self.templates = nn.Parameter(torch.zeros(num_classes, *verts.shape)) if cfg.category_templates else None
        self.register_buffer("faces", faces, persistent=False)
        self.register_buffer("edges", unique_edges(faces, verts.shape[0]), persistent=False)
        self.pooler = (
            single_level_pooler(cfg.feature, feature_stride, cfg.vertalign_resolution)
            if cfg.sampler == "vertalign"
            else None
        )
        self.stages = nn.ModuleList(
            RefinementStage(feature_channels, cfg.hidden_dim, cfg.num_graph_convs, cfg.graph_conv_init)
            for _ in range(cfg.num_stages)
        )

    def forward(self, features: Mapping[str, Tensor], boxes: list[Tensor], labels: Tensor | None = None) -> ShapePrediction:
        """Deform one sphere per box; ``boxes`` is a list over images of (N_i, 4) input-pixel boxes,
        ``labels`` the (N,) flat category indices (needed with category templates)."""
        flat_boxes = torch.cat(boxes).float()
        image_index = torch.repeat_interleave(
            torch.arange(len(boxes), device=flat_boxes.device), torch.tensor([len(b) for b in boxes], device=flat_boxes.device)
        )
        verts = self.sphere_verts.expand(len(flat_boxes), -1, -1)
        if self.templates is not None:
            if labels is None:
                raise ValueError("ShapeHead: model.shape.category_templates needs the objects' labels")
            verts = verts + self.templates[labels.long()]
        roi_features = self.pooler(features, boxes) if self.pooler is not None else None
        stage_verts, offsets = [], []
        for stage in self.stages:
            if roi_features is None:
                vertex_features = roimap_features(features[self.cfg.feature], self.stride, verts, flat_boxes, image_index)
            else:
                vertex_features = vertalign_features(roi_features, verts)
            offset = stage(verts, vertex_features, self.edges).float()
            verts = verts + torch.tanh(offset)
            stage_verts.append(verts)
            offsets.append(offset)
        return ShapePrediction(verts=verts, stage_verts=stage_verts, offsets=offsets)
