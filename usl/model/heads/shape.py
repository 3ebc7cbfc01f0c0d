"""Shape head (paper Sec. 3.3): an identical ico-sphere per object, deformed in the normalized cube.

Each of S refinement stages samples a feature per vertex from one or more backbone maps (or the
input image itself, as a stride-1 map, when ``features`` names ``image``), concatenated (RoIMap,
or RoIAlign + VertAlign for the ablation), projects it to ``hidden_dim``
(Mesh R-CNN's bottleneck), runs ``num_graph_convs`` GraphConvs on [features, positions] and
predicts offsets with a Linear on [features, positions]: ``dV_i = tanh(offset)``,
``V_i = V_{i-1} + dV_i``. With ``pass_features`` (Mesh R-CNN) a stage's last GraphConv output also
enters the next stage's first GraphConv. As the paper states, V_0 (the unit sphere) and each dV_i
lie in [-1, 1]; V itself is not clamped (a clamp would stop the gradient of any vertex that
touches the cube's faces), and the frustum map guards points beyond the far plane
(``usl.geometry.frustum``). The pre-tanh offsets are kept for the ½‖dV‖² regularizer.
``global_stage`` (an option, on in ``tiny``) adds a stage before the others that sees the whole
object: an MLP from the box's flattened RoIAlign features to every vertex's offset,
``V_g = V_0 + tanh(MLP)`` (CMR's shape decoder); its pre-tanh offsets join the regularizer's like
any stage's.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

import torch
from torch import nn

from usl.geometry import MeshTemplate, ico_sphere
from usl.model.backbone import ShapeSpec
from usl.model.config import ShapeHeadConfig
from usl.utils.transfer import to_device

from .graph_conv import GraphConv
from .vertex_features import roimap_features, single_level_pooler, vertalign_features

Tensor = torch.Tensor

# The global stage's learning-rate factor: at the full rate its tanh can saturate within a few hundred
# iterations (a tiny run lost one seed of two that way); at a tenth every run learned
GLOBAL_STAGE_LR_FACTOR = 0.1
VERTALIGN_RESOLUTION = 14  # RoIAlign size of the VertAlign ablation (Mesh R-CNN's ROI_MESH_HEAD.POOLER_RESOLUTION)


@dataclass
class ShapePrediction:
    verts: Tensor  # (N, V, 3) final vertices V_S in the normalized cube
    stage_verts: list[Tensor]  # V_g (with the global stage), then V_1 .. V_S, each (N, V, 3)
    offsets: list[Tensor]  # pre-tanh offsets of each stage, (N, V, 3)


class RefinementStage(nn.Module):
    """One {vertex features, GraphConvs, offsets} stage.

    ``previous_dim``: width of the previous stage's vertex features this stage receives (0: none);
    they join the first GraphConv's input, as in Mesh R-CNN's refinement stages.
    """

    def __init__(
        self,
        feature_dim: int,
        hidden_dim: int,
        num_graph_convs: int,
        graph_conv_init: str = "normal",
        previous_dim: int = 0,
        bottleneck_init: str = "torch",
    ):
        super().__init__()
        self.bottleneck = nn.Linear(feature_dim, hidden_dim)
        if bottleneck_init == "normal":  # Mesh R-CNN's; "torch" keeps nn.Linear's default
            nn.init.normal_(self.bottleneck.weight, std=0.01)
            nn.init.zeros_(self.bottleneck.bias)
        widths = [hidden_dim + previous_dim] + [hidden_dim] * (num_graph_convs - 1)
        self.gconvs = nn.ModuleList(GraphConv(width + 3, hidden_dim, graph_conv_init) for width in widths)
        self.offset = nn.Linear(hidden_dim + 3, 3)
        nn.init.zeros_(self.offset.weight)  # start from the sphere (Mesh R-CNN's init)
        nn.init.zeros_(self.offset.bias)

    def forward(
        self, verts: Tensor, vertex_features: Tensor, edges: Tensor, previous: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """Pre-tanh offsets (N, V, 3) and the last GraphConv's features (N, V, hidden_dim)."""
        positions = verts.to(vertex_features.dtype)
        x = torch.relu(self.bottleneck(vertex_features))
        if previous is not None:
            x = torch.cat([x, previous.to(x.dtype)], dim=-1)
        for gconv in self.gconvs:
            x = torch.relu(gconv(torch.cat([x, positions], dim=-1), edges))
        return self.offset(torch.cat([x, positions], dim=-1)), x


def global_deformation_mlp(roi_dim: int, width: int, num_outputs: int) -> nn.Sequential:
    """RoI features -> 3 numbers per output (a vertex's pre-tanh offset); the last layer starts at
    zero, so the stage starts as the identity (the sphere), like the refinement stages."""
    if roi_dim <= 0:
        raise ValueError(f"model.shape.global_stage={width} needs the RoI features' size (roi_dim), got {roi_dim}")
    last = nn.Linear(width, 3 * num_outputs)
    nn.init.zeros_(last.weight)
    nn.init.zeros_(last.bias)
    return nn.Sequential(nn.Linear(roi_dim, width), nn.ReLU(), nn.Linear(width, width), nn.ReLU(), last)


class ShapeHead(nn.Module):
    """``input_shape``: the backbone's maps by name; ``cfg.features`` picks and orders the sampled ones.
    ``roi_dim`` is the size of one object's flattened RoI features, the global stage's input
    (``cfg.global_stage``)."""

    def __init__(self, input_shape: Mapping[str, ShapeSpec], cfg: ShapeHeadConfig, roi_dim: int = 0):
        super().__init__()
        missing = [name for name in cfg.features if name not in input_shape]
        if missing:
            raise ValueError(f"model.shape.features: no map named {missing}; the maps are {sorted(input_shape)}")
        self.cfg = cfg
        self.strides = [input_shape[name].stride for name in cfg.features]
        verts, faces = ico_sphere(cfg.ico_level)
        self.register_buffer("sphere_verts", verts, persistent=False)
        self.register_buffer("faces", faces, persistent=False)
        template = MeshTemplate.build(faces, verts.shape[0])
        self.register_buffer("edges", template.edges, persistent=False)
        self.register_buffer("edge_faces", template.edge_faces, persistent=False)
        self.poolers = (
            nn.ModuleList(
                single_level_pooler(name, stride, VERTALIGN_RESOLUTION)
                for name, stride in zip(cfg.features, self.strides, strict=True)
            )
            if cfg.sampler == "vertalign"
            else None
        )
        feature_dim = sum(input_shape[name].channels for name in cfg.features)
        self.global_mlp = global_deformation_mlp(roi_dim, cfg.global_stage, len(verts)) if cfg.global_stage else None
        self.stages = nn.ModuleList(
            RefinementStage(
                feature_dim,
                cfg.hidden_dim,
                cfg.num_graph_convs,
                cfg.graph_conv_init,
                previous_dim=cfg.hidden_dim if cfg.pass_features and index > 0 else 0,
                bottleneck_init=cfg.bottleneck_init,
            )
            for index in range(cfg.num_stages)
        )

    @property
    def template(self) -> MeshTemplate:
        """The ico-sphere's connectivity, shared by every predicted mesh (on the module's device)."""
        return MeshTemplate(self.faces, self.edges, self.edge_faces)

    def forward(
        self,
        features: Mapping[str, Tensor],
        boxes: list[Tensor],
        roi: Tensor | None = None,
    ) -> ShapePrediction:
        """Deform one sphere per box; ``boxes`` is a list over images of (N_i, 4) input-pixel boxes,
        ``roi`` the (N, ...) RoI features of the boxes (needed with the global stage)."""
        flat_boxes = torch.cat(boxes).float()
        image_index = torch.repeat_interleave(
            torch.arange(len(boxes), device=flat_boxes.device),
            to_device([len(b) for b in boxes], flat_boxes.device),
            output_size=len(flat_boxes),
        )
        verts = self.sphere_verts.expand(len(flat_boxes), -1, -1)
        maps = [features[name] for name in self.cfg.features]
        roi_features = None if self.poolers is None else [pooler(features, boxes) for pooler in self.poolers]
        stage_verts, offsets, previous = [], [], None
        if self.global_mlp is not None:
            if roi is None:
                raise ValueError("model.shape.global_stage needs the boxes' RoI features (roi=...)")
            offset = self.global_mlp(roi.flatten(1)).float().unflatten(-1, (-1, 3))
            verts = verts + torch.tanh(offset)
            stage_verts.append(verts)
            offsets.append(offset)
        for stage in self.stages:
            if roi_features is None:
                vertex_features = roimap_features(maps, self.strides, verts, flat_boxes, image_index)
            else:
                vertex_features = torch.cat([vertalign_features(pooled, verts) for pooled in roi_features], dim=-1)
            offset, stage_features = stage(verts, vertex_features, self.edges, previous)
            offset = offset.float()
            previous = stage_features if self.cfg.pass_features else None
            verts = verts + torch.tanh(offset)
            stage_verts.append(verts)
            offsets.append(offset)
        return ShapePrediction(verts=verts, stage_verts=stage_verts, offsets=offsets)
