"""Training/model configuration: nested dataclasses, loaded from YAML recipes with ``key=value`` overrides
(the generic loading machinery is ``usl.config_io``).

A recipe (``usl/configs/<name>.yaml`` or any path) holds only what differs from the dataclass
defaults; ``_base_: other.yaml`` inherits another recipe first. Overrides use dotted keys
(``optim.lr=0.01``, ``model.shape.num_stages=1``) and YAML values (``data.root=/data/hs``,
``optim.steps=[60000,75000]``). Unknown keys and ill-typed values are errors that name the key
and the file, so a typo never silently trains with a default. The resolved config (every field)
is saved in the run folder and in each checkpoint; the keys of options since removed
(``REMOVED_OPTIONS``) still load there at their "off" value.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import yaml

from usl.config_io import (  # noqa: F401  (re-exported: usl.config is where callers import them)
    ConfigError,
    deep_merge,
    drop_removed_keys,
    from_dict,
    parse_overrides,
    read_yaml_config,
    to_dict,
)
from usl.losses import LossWeights, PiecewiseLinear
from usl.model.detector import DetectorConfig
from usl.model.pretrained import FORMATS as INIT_FORMATS
from usl.model.pretrained import trained_stride_in_1x1
from usl.render import SoftRasterSettings

CONFIG_DIR = Path(__file__).resolve().parent / "configs"


@dataclass
class DataConfig:
    root: str = ""  # records folder (docs/design.md §3)
    train_split: str = "train"  # split the model trains on
    val_split: str = "val"  # split of the periodic validation (``val.*``) and of usl-eval's default
    num_views: int = 5  # M: the input view plus M - 1 other views
    view_sampling: str = "uniform"  # "uniform" | "time_distance" (p ∝ |view_id difference|, video data)
    input_view_stride: int = 1  # every k-th view of a scene is an input view (video data is redundant)
    max_size: int = 0  # resize so the longer image side is at most this; 0 keeps the stored size
    max_objects: int = 0  # objects of the input view in L_3D (a random subset); 0 keeps all
    # Probability of mirroring a training sample left-right: all its views, as one reflection of
    # the world (usl.data.mirror), so the multi-view geometry stays exact. 0: never (the paper).
    flip_prob: float = 0.0
    num_workers: int = 2  # data loader processes (0: load in the training process)
    verify: str = "size"  # shard checks on open: "size" (a stat) or "sha256" (reads each shard once more)

    def __post_init__(self) -> None:
        _check_choice("data.view_sampling", self.view_sampling, ("uniform", "time_distance"))
        _check_choice("data.verify", self.verify, ("size", "sha256"))
        _check_positive("data.num_views", self.num_views)
        _check_positive("data.input_view_stride", self.input_view_stride)
        if not 0.0 <= self.flip_prob <= 1.0:
            raise ConfigError(f"data.flip_prob must be in [0, 1], got {self.flip_prob}")


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
        _check_choice("model.shape.sampler", self.sampler, ("roimap", "vertalign"))
        _check_choice("model.shape.graph_conv_init", self.graph_conv_init, ("normal", "kaiming"))
        _check_choice("model.shape.bottleneck_init", self.bottleneck_init, ("torch", "normal"))
        _check_positive("model.shape.num_stages", self.num_stages)
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
    layout_range: LayoutRange = field(default_factory=LayoutRange)
    # Local pretrained checkpoint for the whole detector (never downloaded): a torchvision
    # maskrcnn_resnet50_fpn or resnet50 state dict, or a detectron2 model zoo / MSRA R-50 .pkl
    # (usl.model.pretrained). "auto" tells the formats apart by suffix (.pkl: detectron2).
    init_weights: str = ""
    init_format: str = "auto"  # "auto" | "torchvision" | "detectron2"

    def __post_init__(self) -> None:
        _check_choice("model.init_format", self.init_format, INIT_FORMATS)
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
        _check_choice("loss.xent_gate", self.xent_gate, ("iou", "all"))
        _check_choice("loss.supervision", self.supervision, ("2d", "3d"))
        for name in ("dist", "soft_iou"):
            if getattr(self.weights, name) < 0:
                raise ConfigError(f"loss.weights.{name}: must be >= 0, got {getattr(self.weights, name)}")


@dataclass
class OptimConfig:
    name: str = "sgd"  # "sgd" | "adam"
    lr: float = 0.01  # base learning rate (for the whole batch of all processes)
    momentum: float = 0.9  # SGD momentum (ignored by Adam)
    weight_decay: float = 1e-4  # L2 penalty on the weights
    schedule: str = "step"  # "step" (x gamma at each of steps) | "constant"
    steps: tuple[int, ...] = ()  # iterations at which the "step" schedule multiplies the rate by gamma
    gamma: float = 0.1  # factor of each step
    warmup_iters: int = 0  # linear warm-up length (0: none)
    warmup_factor: float = 0.001  # rate at iteration 0 of the warm-up, as a fraction of lr
    max_iter: int = 1000  # iterations to train
    # Clip the whole gradient's norm at this, against rare gradient spikes after which a run can stall
    # (tiny's global stage sends them). 0 disables clipping (the norm is still checked for NaN/inf).
    clip_grad_norm: float = 0.0
    # Learning-rate factors by parameter-name prefix, e.g. {shape_head: 10}: the longest matching
    # prefix wins, other parameters keep lr. Empty: one rate for the whole model (the paper).
    lr_mult: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        _check_choice("optim.name", self.name, ("sgd", "adam"))
        _check_choice("optim.schedule", self.schedule, ("step", "constant"))
        _check_positive("optim.max_iter", self.max_iter)
        bad = {k: v for k, v in self.lr_mult.items() if not v > 0}
        if bad:
            raise ConfigError(f"optim.lr_mult: factors must be > 0, got {bad}")


@dataclass
class TrainConfig:
    batch_size: int = 2  # input images per process (GPU)
    seed: int = 0  # seeds data order, sampling and initialisation
    device: str = "auto"  # "auto" (a GPU per process if there are enough, else the CPU) | "cpu" | "cuda"
    amp: str = "bfloat16"  # autocast dtype on CUDA: "bfloat16" | "float16" | "none"; ignored on CPU
    log_every: int = 20  # iterations between rows of metrics.csv and lines of log.txt
    checkpoint_every: int = 1000  # iterations between checkpoints (and one at the end)
    keep_checkpoints: int = 3  # newest checkpoints kept in the run folder (0 keeps all)
    cpu_threads: int = 0  # torch intra-op threads per process; 0 leaves torch's default
    # On CPU, keep freed heap memory in the process (glibc's mmap and trim thresholds raised by
    # TrainStep, usl.engine.cpu_memory): steps stop re-faulting their tensors page by page. The
    # process keeps its peak memory; false leaves glibc's defaults.
    retain_freed_memory: bool = True
    # Stop when more than this fraction of the last ``skip_window`` steps were skipped as non-finite
    # (corrupt data or divergence, not a rare outlier); 1.0 never stops.
    max_skipped_fraction: float = 0.25
    skip_window: int = 20  # recent steps the skipped fraction is counted over

    def __post_init__(self) -> None:
        _check_choice("train.amp", self.amp, ("bfloat16", "float16", "none"))
        _check_choice("train.device", self.device, ("auto", "cpu", "cuda"))
        _check_positive("train.batch_size", self.batch_size)
        _check_positive("train.skip_window", self.skip_window)
        if not 0.0 <= self.max_skipped_fraction <= 1.0:
            raise ConfigError(f"train.max_skipped_fraction: {self.max_skipped_fraction} is not in [0, 1]")


@dataclass
class ValidationConfig:
    """Periodic validation during training: a quick subset of ``usl-eval`` on ``data.val_split``."""

    period: int = 500  # iterations between validations, plus one at the end; 0 disables validation
    num_scenes: int = 4  # the first N scenes of the split (0: all)
    input_views: str = "first"  # input views per scene, as usl-eval --input-views (all | first | every:K | ...)
    samples_3d: int = 1000  # points per mesh for Chamfer / F1 when the split has 3D ground truth

    def __post_init__(self) -> None:
        if self.period < 0 or self.num_scenes < 0:
            raise ConfigError(f"val.period and val.num_scenes must be >= 0, got {self.period}, {self.num_scenes}")


@dataclass
class Config:
    name: str = "usl"  # the run's name; default run folder: runs/<name>
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    val: ValidationConfig = field(default_factory=ValidationConfig)


def _check_choice(key: str, value: str, choices: Sequence[str]) -> None:
    if value not in choices:
        raise ConfigError(f"{key}: {value!r} is not one of {list(choices)}")


def _check_positive(key: str, value: int) -> None:
    if value < 1:
        raise ConfigError(f"{key}: must be >= 1, got {value}")


# --------------------------------------------------------------------------------------------
# The recipes: a checked Config from YAML files and overrides
# --------------------------------------------------------------------------------------------
def resolve_config_path(name_or_path: str | Path) -> Path:
    """A recipe name (``tiny``, ``hypersim``) from ``usl/configs`` or a path to a YAML file."""
    path = Path(name_or_path)
    if path.suffix not in (".yaml", ".yml"):
        path = CONFIG_DIR / f"{name_or_path}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in CONFIG_DIR.glob("*.yaml"))
        raise ConfigError(f"config {name_or_path!r}: no such file {path} (built-in recipes: {known})")
    return path


def load_config(name_or_path: str | Path, overrides: Sequence[str] = ()) -> Config:
    """Defaults <- recipe (with its ``_base_`` chain) <- overrides, checked and typed.

    A mistake in the recipe is reported against its file; one in the overrides against the
    command line and the override that makes it."""
    path = resolve_config_path(name_or_path)
    recipe = read_yaml_config(path)
    config = config_from_dict(recipe, where=str(path))
    return apply_overrides(recipe, overrides) if overrides else config


def apply_overrides(base: Mapping[str, Any], overrides: Sequence[str]) -> Config:
    """``base`` (a valid nested config dict) with command-line ``key=value`` overrides on top."""
    update = parse_overrides(overrides)
    try:
        return config_from_dict(deep_merge(base, update), where="command line")
    except ConfigError as exc:
        culprit = next((o for o in overrides if not _applies(base, o)), None)
        if culprit is None:  # only the combination fails (e.g. a value checked against another)
            raise
        raise ConfigError(f"{exc} (override {culprit!r})") from None


def _applies(base: Mapping[str, Any], override: str) -> bool:
    try:
        config_from_dict(deep_merge(base, parse_overrides([override])))
    except ConfigError:
        return False
    return True


# Options measured, found not to help and removed (docs/experiments/removed-options.md names the commit
# that has them), with what to do instead. Every saved config (run folder, checkpoint) carries every
# field, so one written before the removal holds them at their "off" value, and still loads.
_INSTEAD = {
    **{
        f"data.color_jitter.{name}": "the input images are used as stored"
        for name in ("brightness", "contrast", "saturation", "hue")
    },
    "model.shape.category_templates": "every object starts from the ico-sphere",
    "model.shape.global_basis": "the global stage predicts one offset per vertex",
    "model.shape.feature": "set model.shape.features, a list of map names (e.g. [p2])",
    "model.detector.backbone.resnet.weights": "set model.init_weights (a whole-detector or ResNet checkpoint)",
    "loss.dist_vertices": "l_dist uses the surface samples only",
    "loss.weights.depth_laplacian": "use loss.weights.laplacian or loss.weights.normal",
}
REMOVED_OPTIONS = {key: f"{instead} (docs/experiments/removed-options.md)" for key, instead in _INSTEAD.items()}


def config_from_dict(data: Mapping[str, Any], where: str = "config") -> Config:
    """A full ``Config`` from a (possibly partial) nested dict over the defaults."""
    data = drop_removed_keys(data, REMOVED_OPTIONS, where)
    defaults = to_dict(Config())
    model = data.get("model") if isinstance(data.get("model"), Mapping) else {}
    preset = model.get("detector_preset", "default")
    if preset not in DETECTOR_PRESETS:
        raise ConfigError(f"{where}: model.detector_preset: {preset!r} is not one of {sorted(DETECTOR_PRESETS)}")
    defaults["model"]["detector"] = to_dict(DETECTOR_PRESETS[preset]())
    merged = deep_merge(defaults, data)
    try:
        return from_dict(Config, merged, "config")
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def dump_config(config: Config) -> str:
    """The resolved config (every field) as YAML, in definition order."""
    return yaml.safe_dump(to_dict(config), sort_keys=False)


def save_config(config: Config, path: str | Path) -> None:
    """Write the resolved config (every field) as YAML."""
    Path(path).write_text(dump_config(config))
