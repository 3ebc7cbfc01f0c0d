"""The ``model`` and ``loss`` sections of the config: the detector, the layout and shape heads, and the
training losses ``USLModel`` builds from them (``usl.model.usl_model``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from usl.config_io import ConfigError, check_choice, check_positive
from usl.losses import LossWeights, PiecewiseLinear
from usl.model.detector import DetectorConfig
from usl.model.pretrained import FORMATS as INIT_FORMATS
from usl.model.pretrained import trained_stride_in_1x1
from usl.render import SoftRasterSettings


@dataclass
class LayoutRange:
    """``z = z0 + z~ (z1 - z0)``, ``rho = rho0 + rho~ (rho1 - rho0)`` (metres, data_specs ``layout``)."""

    z0: float = 0.0  # nearest object depth (metres); all four come from the manifest when z1 is 0
    z1: float = 0.0  # farthest object depth (metres)
    rho0: float = 0.0  # smallest object extent in depth (metres)
    rho1: float = 0.0  # largest object extent in depth (metres)

    def from_unit(self, z_unit: Any, rho_unit: Any) -> tuple[Any, Any]:
        """(z, rho) in metres from their positions in [0, 1] along the ranges (floats or tensors)."""
        return self.z0 + z_unit * (self.z1 - self.z0), self.rho0 + rho_unit * (self.rho1 - self.rho0)


@dataclass
class LayoutHeadConfig:
    in_features: tuple[str, ...] = ("p2",)  # paper Appendix tables: RoIAlign on FPN p2
    pooler_resolution: int = 7  # RoIAlign bins, then averaged to one 1 x C vector
    num_fc: int = 4  # fully connected layers before the per-category z~, rho~ sigmoids
    fc_dim: int = 256  # width of each of them
    # Also feed the MLP the 2D box as camera rays (K^-1 at its corners, and its log width and
    # height): RoIAlign resamples every box to the same grid, so the pooled features lose the
    # apparent size and image height that tell depth apart. Not in the paper (False there).
    box_geometry: bool = False


@dataclass
class ShapeHeadConfig:
    ico_level: int = 3  # subdivisions of the initial ico-sphere (3: 642 vertices, 4: 2562)
    num_stages: int = 3  # refinement stages S, each {vertex features, graph convs, offsets}
    num_graph_convs: int = 3  # graph convolutions per stage
    hidden_dim: int = 256  # width of the bottleneck and the graph convolutions
    # Backbone maps sampled at each vertex's projection (each at its own stride) and concatenated:
    # [p2] (the paper's FPN recipes) or [res2, res3, res4, res5] (Mesh R-CNN's ShapeNet model, R50);
    # "image" names the normalised input image itself (3 channels, stride 1), e.g. [p2, image]
    features: tuple[str, ...] = ("p2",)
    # Mesh R-CNN: each stage's last GraphConv output is concatenated into the next stage's first
    # GraphConv input (its width grows by hidden_dim); False: stages share only the vertex positions
    pass_features: bool = False
    sampler: str = "roimap"  # "roimap" (paper) | "vertalign" (Mesh R-CNN's: Table 1's "w/o RoIMap")
    vertalign_resolution: int = 14  # RoIAlign size of the VertAlign ablation
    # GraphConv weight init: "normal" N(0, 0.01²) (Mesh R-CNN) | "kaiming" (He init for the
    # neighbourhood sum): with "normal" three GraphConvs pass ~1% of the image features on
    graph_conv_init: str = "normal"
    # Bottleneck Linear init: "torch" (PyTorch's default, uniform with std 1/sqrt(3 fan_in)) |
    # "normal" (N(0, 0.01²), bias 0: Mesh R-CNN's)
    bottleneck_init: str = "torch"
    # Width of a global deformation stage before the refinement stages: an MLP from the object's
    # RoIAlign features (the layout head's pooled input, flattened) to an offset of every vertex,
    # V_g = sphere + tanh(MLP), each vertex with output weights of its own (CMR's shape decoder).
    # A refinement stage sees one pixel per vertex and ~6 graph hops; this stage sees the whole
    # object at once, so an offset may follow from what the image shows anywhere in the box. It
    # learns stably at a tenth of the rate (optim.lr_mult={shape_head.global_mlp: 0.1}, tiny's): at
    # the full rate its tanh can saturate within a few hundred iterations. 0: the paper's head.
    global_stage: int = 0

    def __post_init__(self) -> None:
        check_choice("model.shape.sampler", self.sampler, ("roimap", "vertalign"))
        check_choice("model.shape.graph_conv_init", self.graph_conv_init, ("normal", "kaiming"))
        check_choice("model.shape.bottleneck_init", self.bottleneck_init, ("torch", "normal"))
        check_positive("model.shape.num_stages", self.num_stages)
        if self.global_stage < 0:
            raise ConfigError(f"model.shape.global_stage: must be >= 0 (0: none), got {self.global_stage}")
        if not self.features or len(set(self.features)) != len(self.features):
            raise ConfigError(f"model.shape.features: need distinct backbone map names, got {list(self.features)}")


DETECTOR_PRESETS = {"default": DetectorConfig, "r50": DetectorConfig.r50, "tiny": DetectorConfig.tiny}


@dataclass
class ModelConfig:
    # Defaults the ``detector`` section starts from: "default" (Mask R-CNN R50-FPN), "r50" (a plain
    # R50 exposing res2..res5, RPN and RoI heads on res4: ``DetectorConfig.r50()``) or "tiny"
    # (``DetectorConfig.tiny()``, for CPU runs); the recipe's ``detector`` keys apply on top.
    detector_preset: str = "default"
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    layout: LayoutHeadConfig = field(default_factory=LayoutHeadConfig)
    shape: ShapeHeadConfig = field(default_factory=ShapeHeadConfig)
    # Filled from the records manifest when empty (categories in data_specs order, layout ranges).
    categories: tuple[str, ...] = ()
    category_ids: tuple[int, ...] = ()  # the dataset's id of each category (what records, COCO and GLB use)
    layout_range: LayoutRange = field(default_factory=LayoutRange)
    # Local pretrained checkpoint for the whole detector (never downloaded): a torchvision
    # maskrcnn_resnet50_fpn or resnet50 state dict, or a detectron2 model zoo / MSRA R-50 .pkl
    # (usl.model.pretrained). "auto" tells the formats apart by suffix (.pkl: detectron2).
    init_weights: str = ""
    init_format: str = "auto"  # "auto" | "torchvision" | "detectron2"

    def __post_init__(self) -> None:
        check_choice("model.init_format", self.init_format, INIT_FORMATS)
        resnet = self.detector.backbone.resnet
        if resnet.stride_in_1x1 is None and self.init_weights:  # the ResNet variant the weights were trained as
            resnet.stride_in_1x1 = trained_stride_in_1x1(self.init_weights, self.init_format)


_SOFT = SoftRasterSettings()


@dataclass
class RenderConfig:
    """Dynamic soft rendering for l_xent; defaults are ``usl.render.SoftRasterSettings``'s."""

    resolution: int = 72  # side of every dynamic-rendering window (paper: 128 Scene-Shapes, 72 others)
    sigma: float = _SOFT.sigma  # sharpness of the soft silhouette (SoftRas sigma)
    blur_radius: float = _SOFT.blur_radius  # faces farther than this from a pixel do not touch it
    # the nearest faces by depth blended per pixel; null blends every face within the blur radius
    # (SoftRas), which skips the per-pixel depth sort
    faces_per_pixel: int | None = _SOFT.faces_per_pixel
    padding: float = 0.05  # window margin, as a fraction of its longer side

    def settings(self) -> SoftRasterSettings:
        return SoftRasterSettings(sigma=self.sigma, blur_radius=self.blur_radius, faces_per_pixel=self.faces_per_pixel)


@dataclass
class Mesh3DLossConfig:
    """Mesh R-CNN's 3D mesh losses (``loss.supervision=3d``). Defaults: its ShapeNet config
    (meshrcnn ``configs/shapenet``: CHAMFER_LOSS_WEIGHT 1.0, NORMALS_LOSS_WEIGHT 0.0, EDGE_LOSS_WEIGHT 0.2,
    GT_NUM_SAMPLES = PRED_NUM_SAMPLES = 5000)."""

    chamfer: float = 1.0  # Chamfer-L2 between points on the predicted and the true mesh (m^2)
    normals: float = 0.0  # 1 - |cos| between the normals of nearest point pairs, both ways
    edge: float = 0.2  # squared edge length of the predicted mesh in the camera frame (m^2)
    num_samples: int = 5000  # points sampled on each predicted and each true mesh


@dataclass
class LossConfig:
    weights: LossWeights = field(default_factory=LossWeights)
    render: RenderConfig = field(default_factory=RenderConfig)
    # l_dist is a squared distance in units of the image's longer side; this factor sets its unit
    # against l_xent (a per-pixel mean) and the regularizers (the paper leaves the unit open).
    # 1024 = (1/32 of the longer side)^-2: an error of 1/32 of the image costs 1, so the layout
    # signal is not drowned by l_xent and the regularizers at any image resolution.
    dist_scale: float = 1024.0
    # Factor on dist_scale by iteration (piecewise linear through iters/values; empty = 1, the
    # paper's constant balance). E.g. {iters: [300, 900], values: [1.0, 0.25]} lets l_dist place
    # the layout first, then hands the shape to l_xent.
    dist_schedule: PiecewiseLinear = field(default_factory=PiecewiseLinear)
    mesh_points: int = 1000  # points sampled on each mesh surface for l_dist
    mask_points: int = 1000  # points sampled in each true silhouette for l_dist
    # The IoU gate of Eq. 4, the key Table 1's ablations vary: with loss.xent_gate=iou, l_xent applies
    # to an (object, view) pair only when IoU(rendered > 0.5, true) exceeds this (paper: 0.5).
    iou_threshold: float = 0.5
    # Which pairs l_xent applies to: "iou" (paper Eq. 4, also for Table 1's "w/o l_dist" row: only
    # l_dist is removed) or "all" (no gate: to ablate Eq. 4's gate). Without l_dist neither trains at
    # CPU scale: gated, other-view pairs fall below the threshold and z, rho get no gradient;
    # ungated, l_xent drives z and rho to the ends of their range, where the silhouettes vanish.
    xent_gate: str = "iou"
    # The gate exists because l_xent says nothing about layout when silhouettes do not overlap.
    # In the input view they always do: the 2D box fixes the projection whatever z and rho are.
    # False applies l_xent there ungated, so thin objects (tables start at IoU ~0.2) get a shape
    # signal from the first step; True is the paper's gate in every view.
    gate_input_view: bool = True
    # True masks show only visible parts. True: cells covered by another object's true mask are
    # left out of this object's l_xent (it may be hidden there), instead of teaching it to carve
    # away what an occluder covers. False: the paper's per-object comparison.
    ignore_occluders: bool = False
    # "2d": the paper's multi-view silhouette loss L_3D. "3d": Mesh R-CNN's losses against the
    # objects table's true meshes instead (Table 1's "Mesh R-CNN (3D sup.)" upper bound, Scene-Shapes
    # only): Chamfer, normal and edge terms on points in the input camera's frame (loss.mesh3d).
    supervision: str = "2d"
    mesh3d: Mesh3DLossConfig = field(default_factory=Mesh3DLossConfig)

    def __post_init__(self) -> None:
        check_choice("loss.xent_gate", self.xent_gate, ("iou", "all"))
        check_choice("loss.supervision", self.supervision, ("2d", "3d"))
        for name in ("dist", "soft_iou"):
            if getattr(self.weights, name) < 0:
                raise ConfigError(f"loss.weights.{name}: must be >= 0, got {getattr(self.weights, name)}")
