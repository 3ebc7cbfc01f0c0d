"""The ``model`` and ``loss`` sections of the config: the detector, the layout and shape heads, and the
training losses ``USLModel`` builds from them (``usl.model.usl_model``)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

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
    in_features: tuple[str, ...] = ("p2",)  # backbone maps RoIAligned per box (paper: FPN p2)
    num_fc: int = 4  # fully connected layers before the per-category z~, rho~ sigmoids (fewer: faster)
    fc_dim: int = 256  # width of each of them (smaller: faster)
    # Also read the 2D box as camera rays (its corners through K^-1, log width and height): RoIAlign
    # loses the apparent size that tells depth apart. False: RoI features only (the paper)
    box_geometry: bool = True


@dataclass
class ShapeHeadConfig:
    ico_level: int = 3  # subdivisions of the initial ico-sphere (2: 162 vertices, 3: 642, 4: 2562)
    num_stages: int = 3  # refinement stages S, each {vertex features, graph convs, offsets}; more: finer, slower
    num_graph_convs: int = 3  # graph convolutions per stage (more: a wider reach on the mesh, slower)
    hidden_dim: int = 256  # width of the bottleneck and the graph convolutions (smaller: faster)
    # Maps sampled at each vertex and concatenated: [p2] (FPN), [res2, res3, res4, res5] (plain R50),
    # "image" the normalised input image (stride 1): colour that from-scratch features blur
    features: tuple[str, ...] = ("p2",)
    pass_features: bool = False  # each stage's last GraphConv output goes into the next (Mesh R-CNN's, not the paper's)
    sampler: str = "roimap"  # "roimap" (paper) | "vertalign" (Mesh R-CNN's: Table 1's "w/o RoIMap")
    # GraphConv init: "normal" N(0, 0.01²) (Mesh R-CNN's; passes ~1% of the image features on after
    # three convs) | "kaiming" (He init: the features reach the offsets, for short runs)
    graph_conv_init: str = "normal"
    bottleneck_init: str = "torch"  # bottleneck Linear init: "torch" (PyTorch's) | "normal" (Mesh R-CNN's N(0, 0.01²))
    # Width of an MLP from the box's RoIAlign features to every vertex's offset, before the refinement
    # stages: the whole object decides the shape (it learns at lr / 10). 0: none (the paper)
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
    # Defaults the ``detector`` keys start from: "default" (Mask R-CNN R50-FPN), "r50" (plain R50, heads
    # on res4: DetectorConfig.r50) or "tiny" (quarter-width R18-FPN for CPU runs: DetectorConfig.tiny)
    detector_preset: str = "default"
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    layout: LayoutHeadConfig = field(default_factory=LayoutHeadConfig)
    shape: ShapeHeadConfig = field(default_factory=ShapeHeadConfig)
    categories: tuple[str, ...] = ()  # category names; empty: the records manifest's, in data_specs order
    category_ids: tuple[int, ...] = ()  # the dataset's id of each category (what records, COCO and GLB use)
    layout_range: LayoutRange = field(default_factory=LayoutRange)
    # Local pretrained checkpoint for the detector (never downloaded): torchvision's Mask R-CNN or ResNet-50
    # .pth, or a detectron2 model zoo / MSRA R-50 .pkl (usl.model.pretrained)
    init_weights: str = ""
    init_format: str = "auto"  # "auto" (by suffix: .pkl is detectron2) | "torchvision" | "detectron2"

    def __post_init__(self) -> None:
        check_choice("model.init_format", self.init_format, INIT_FORMATS)
        resnet = self.detector.backbone.resnet
        if resnet.stride_in_1x1 is None and self.init_weights:  # the ResNet variant the weights were trained as
            resnet.stride_in_1x1 = trained_stride_in_1x1(self.init_weights, self.init_format)


_SOFT = SoftRasterSettings()


@dataclass
class RenderConfig:
    """Dynamic soft rendering for l_xent. ``sigma`` and ``faces_per_pixel`` default to
    ``usl.render.SoftRasterSettings``'s (the paper's); ``blur_radius`` to PyTorch3D's usual reach."""

    padding: ClassVar[float] = 0.05  # window margin, as a fraction of its longer side

    resolution: int = 72  # side of every dynamic-rendering window (paper: 128 Scene-Shapes, 72 others)
    sigma: float = _SOFT.sigma  # sharpness of the soft silhouette (SoftRas sigma): smaller, sharper edges
    # Faces farther than this from a pixel do not touch it: ln(1/1e-4 - 1) sigma, PyTorch3D's usual. At the
    # paper's 1e-3 (= sigma) l_xent shrinks a mesh lying inside its silhouette (too little reach)
    blur_radius: float = 9.21e-3
    # the nearest faces by depth blended per pixel; null blends every face within the blur radius
    # (SoftRas), which skips the per-pixel depth sort
    faces_per_pixel: int | None = _SOFT.faces_per_pixel

    def settings(self) -> SoftRasterSettings:
        return SoftRasterSettings(sigma=self.sigma, blur_radius=self.blur_radius, faces_per_pixel=self.faces_per_pixel)


@dataclass
class LossConfig:
    weights: LossWeights = field(default_factory=LossWeights)
    render: RenderConfig = field(default_factory=RenderConfig)
    # l_dist's unit against l_xent and the regularizers: an error of 1/32 of the image's longer side
    # costs 1 at 1024 = 32², at any resolution (the paper leaves the unit open)
    dist_scale: float = 1024.0
    # Factor on dist_scale by iteration (empty: 1, the paper's): l_dist may place the layout first, then
    # hand the shape over to l_xent, e.g. {iters: [300, 900], values: [1.0, 0.25]}
    dist_schedule: PiecewiseLinear = field(default_factory=PiecewiseLinear)
    mesh_points: int = 1000  # points sampled on each mesh and each true silhouette for l_dist (fewer: faster, noisier)
    iou_threshold: float = 0.5  # the IoU gate of Eq. 4: l_xent applies to an (object, view) above it (paper: 0.5)
    # Pairs l_xent applies to: "iou" (the gate of Eq. 4) | "all" (no gate: Table 1's ablation of it)
    xent_gate: str = "iou"
    # False: no gate in the input view, where the 2D box fixes the silhouette whatever z and rho are,
    # so thin objects get a shape signal from the first step. True: the paper's gate in every view
    gate_input_view: bool = False
    # True masks show visible parts only: True leaves pixels another object's true mask covers out of
    # l_xent, instead of carving away what an occluder hides. False: the paper's
    ignore_occluders: bool = True
    # "2d": the paper's multi-view silhouette loss L_3D | "3d": Mesh R-CNN's losses against the true
    # meshes (Table 1's "Mesh R-CNN (3D sup.)" upper bound; Scene-Shapes only)
    supervision: str = "2d"

    def __post_init__(self) -> None:
        check_choice("loss.xent_gate", self.xent_gate, ("iou", "all"))
        check_choice("loss.supervision", self.supervision, ("2d", "3d"))
        for name in ("dist", "soft_iou"):
            if getattr(self.weights, name) < 0:
                raise ConfigError(f"loss.weights.{name}: must be >= 0, got {getattr(self.weights, name)}")
