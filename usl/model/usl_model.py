"""The full USL model: Mask R-CNN + layout head + shape head + frustum casting (paper Sec. 3).

``model(samples)`` (training) returns the named, weighted losses and their sum under ``"loss"``:
``L = mu_2d L_2D + mu_3D L_3D + mu_reg L_reg``. The 3D heads are trained on the ground-truth
boxes of the input view's objects (the frustum of each object is its true 2D box).

``model.predict(frames, mode)`` returns one ``ObjectPredictions`` per input image:
``mode="gt_boxes"`` uses the true boxes and labels (how the paper measures shape and layout),
``mode="detections"`` the detector's own boxes, labels and scores.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import nn

from usl.data.frames import FrameData
from usl.data.samples import MultiViewSample
from usl.geometry import cube_to_frustum
from usl.losses import combine_losses
from usl.model.backbone import IMAGENET_MEAN, IMAGENET_STD, ShapeSpec
from usl.model.config import LossConfig, ModelConfig
from usl.model.detector import ImageList, MaskRCNN, MultiScaleRoIAlign
from usl.model.detector.roi_heads import CANONICAL_LEVEL, POOLER_SAMPLING_RATIO
from usl.model.heads import LayoutHead, LayoutPrediction, ShapeHead, ShapePrediction
from usl.model.heads.layout import POOLER_RESOLUTION as LAYOUT_POOLER_RESOLUTION
from usl.model.heads.shape import GLOBAL_STAGE_LR_FACTOR
from usl.model.mesh3d_loss import mesh_supervision_loss
from usl.model.multiview_loss import REGULARIZERS, multiview_silhouette_loss, shape_regularizers
from usl.model.ops import autocast_off
from usl.model.outputs import ObjectPredictions
from usl.model.pretrained import init_detector, print_report

Tensor = torch.Tensor
MODES = ("gt_boxes", "detections")
# model.shape.features may name the input image (3 channels at stride 1) next to the backbone's maps
IMAGE_MAP = "image"


@dataclass
class ObjectOutputs:
    """The 3D heads' outputs for N objects of a batch, image by image."""

    layout: LayoutPrediction
    shape: ShapePrediction
    verts_cam: Tensor  # (N, V, 3) meshes in their input camera's frame
    counts: list[int]  # objects per image
    boxes: Tensor  # (N, 4) the boxes the frustums are built on
    K: Tensor  # (N, 3, 3) each object's input camera

    def stage_verts_cam(self) -> list[Tensor]:
        """Every stage's meshes (the global stage's first, if on) in the input camera's frame (the last is ``verts_cam``)."""
        cast = [
            cube_to_frustum(v.float(), self.boxes, self.K, self.layout.z, self.layout.rho)
            for v in self.shape.stage_verts[:-1]
        ]
        return cast + [self.verts_cam]


class USLModel(nn.Module):
    """``load_init_weights=False`` skips ``cfg.init_weights``, for callers that load a full state dict next."""

    def __init__(self, cfg: ModelConfig, loss_cfg: LossConfig | None = None, load_init_weights: bool = True):
        super().__init__()
        if not cfg.categories:
            raise ValueError("ModelConfig.categories is empty: fill it from the dataset (usl.engine.train does)")
        self.cfg = cfg
        self.loss_cfg = loss_cfg or LossConfig()
        self.detector = MaskRCNN(len(cfg.categories), cfg.detector)
        shapes = self.detector.feature_shapes()
        for name in cfg.layout.in_features:
            if name not in shapes:
                raise ValueError(f"model.layout.in_features: backbone has no feature {name!r}; it has {sorted(shapes)}")
        self.layout_pooler = MultiScaleRoIAlign(
            cfg.layout.in_features,
            [shapes[n].stride for n in cfg.layout.in_features],
            LAYOUT_POOLER_RESOLUTION,
            POOLER_SAMPLING_RATIO,
            cfg.detector.roi_heads.canonical_box_size,
            CANONICAL_LEVEL,
        )
        in_channels = shapes[cfg.layout.in_features[0]].channels
        self.layout_head = LayoutHead(in_channels, len(cfg.categories), cfg.layout, cfg.layout_range)
        roi_dim = in_channels * LAYOUT_POOLER_RESOLUTION**2  # the global shape stage reads the layout head's RoIs
        self.shape_head = ShapeHead({**shapes, IMAGE_MAP: ShapeSpec(channels=3, stride=1)}, cfg.shape, roi_dim)
        if cfg.init_weights and load_init_weights:
            print_report(init_detector(self.detector, cfg.init_weights, cfg.init_format))
        self.register_buffer("pixel_mean", torch.tensor(IMAGENET_MEAN).view(3, 1, 1), persistent=False)
        self.register_buffer("pixel_std", torch.tensor(IMAGENET_STD).view(3, 1, 1), persistent=False)

    @property
    def faces(self) -> Tensor:
        """(F, 3) int64 faces shared by every predicted mesh."""
        return self.shape_head.faces

    def lay_out_weights_like_features(self, device: torch.device) -> None:
        """The detector's :meth:`~usl.model.detector.MaskRCNN.lay_out_weights_like_features` (before DDP)."""
        self.detector.lay_out_weights_like_features(device)

    def lr_factors(self) -> dict[str, float]:
        """Learning-rate factors by parameter-name prefix, for parts that need their own rate."""
        return {"shape_head.global_mlp": GLOBAL_STAGE_LR_FACTOR} if self.shape_head.global_mlp is not None else {}

    def prediction_weights(self) -> set[str]:
        """Names of the weights that write a prediction with many outputs (the global stage's vertex
        offsets): optimizers for hidden layers (Muon) leave them to Adam, like the small output layers."""
        mlp = self.shape_head.global_mlp
        return {f"shape_head.global_mlp.{len(mlp) - 1}.weight"} if mlp is not None else set()

    # ------------------------------------------------------------------ shared parts
    def _backbone(self, frames: Sequence[FrameData]) -> tuple[ImageList, dict[str, Tensor]]:
        device = self.pixel_mean.device
        sizes = [frame.size for frame in frames]
        height, width = max(h for h, _ in sizes), max(w for _, w in sizes)
        batch = torch.zeros(len(frames), 3, height, width, device=device)
        for index, frame in enumerate(frames):
            h, w = frame.size
            batch[index, :, :h, :w] = (frame.image.to(device) - self.pixel_mean) / self.pixel_std
        image_list = self.detector.preprocess(batch, sizes)
        features = self.detector.features(image_list)
        if IMAGE_MAP in self.cfg.shape.features:  # the normalised image itself, a stride-1 map
            features = {**features, IMAGE_MAP: image_list.tensor}
        return image_list, features

    def objects(
        self, features: dict[str, Tensor], boxes: list[Tensor], labels: list[Tensor], K: list[Tensor]
    ) -> ObjectOutputs:
        """Layout and shape for the given boxes (per image), cast into each input camera's frame."""
        boxes = [b.float() for b in boxes]
        flat_labels = torch.cat(labels).long()
        counts = [len(b) for b in boxes]
        flat_boxes = torch.cat(boxes)
        flat_K = torch.cat([k.float().expand(n, 3, 3) for k, n in zip(K, counts, strict=True)])
        pooled = self.layout_pooler(features, boxes)
        layout = self.layout_head(pooled, flat_labels, flat_boxes, flat_K)
        shape = self.shape_head(features, boxes, pooled)
        with autocast_off(shape.verts.device.type):
            verts_cam = cube_to_frustum(shape.verts.float(), flat_boxes, flat_K, layout.z, layout.rho)
        return ObjectOutputs(layout, shape, verts_cam, counts, flat_boxes, flat_K)

    # ------------------------------------------------------------------ training
    def forward(
        self, samples: list[MultiViewSample], iteration: int = 0, diagnostics: bool = False
    ) -> dict[str, Tensor]:
        """Weighted losses (``det/*``, ``l3d`` and the weighted regularizers of ``REGULARIZERS``), their sum
        ``loss``, and detached statistics under ``stat/*``.

        ``iteration`` drives the loss schedules (``loss.dist_schedule``). ``diagnostics`` adds the
        gradient norms of l_dist's and the gated l_xent's parts at the shape head's output
        (``stat/grad_dist``, ``stat/grad_xent``) and of L_3D at z and rho (``stat/grad_z``,
        ``stat/grad_rho``): extra backward passes through the loss, none through the network, so
        the trainer asks for them on logging steps only. With ``loss.supervision=3d`` L_3D is Mesh
        R-CNN's loss against the samples' true meshes (``usl.model.mesh3d_loss``)."""
        frames = [s.frame for s in samples]
        image_list, features = self._backbone(frames)
        weights = self.loss_cfg.weights
        detection = None
        if weights.mu_2d:
            targets = [{"boxes": f.boxes, "labels": f.labels, "masks": f.masks} for f in frames]
            detection = self.detector.losses(image_list, features, targets)
        outputs = self.objects(
            features,
            [s.frame.boxes[s.object_rows] for s in samples],
            [s.frame.labels[s.object_rows] for s in samples],
            [s.frame.K for s in samples],
        )
        with autocast_off(outputs.verts_cam.device.type):
            if self.loss_cfg.supervision == "3d":
                l3d, stats = mesh_supervision_loss(outputs.stage_verts_cam(), self.faces, samples, outputs.counts)
            else:
                l3d, stats = self._silhouette_loss(outputs, samples, iteration, diagnostics)
            need = {name: bool(getattr(weights, name)) for name in REGULARIZERS}
            regs = shape_regularizers(
                outputs.shape.verts, outputs.shape.offsets, self.shape_head.template, outputs.counts, need
            )
            # Keep both heads in the graph even for a batch without objects (DDP needs every gradient).
            l3d = l3d + 0.0 * (outputs.layout.z.sum() + outputs.layout.rho.sum() + outputs.shape.verts.sum())
            total, parts = combine_losses(weights, l3d, detection, **regs)
        parts["loss"] = total
        parts.update({f"stat/{k}": v for k, v in stats.items()})
        if outputs.counts and sum(outputs.counts):
            parts["stat/z"] = outputs.layout.z.detach().mean()
            parts["stat/rho"] = outputs.layout.rho.detach().mean()
        return parts

    def _silhouette_loss(
        self, outputs: ObjectOutputs, samples: list[MultiViewSample], iteration: int, diagnostics: bool
    ) -> tuple[Tensor, dict[str, Tensor]]:
        """The paper's multi-view L_3D and its statistics (with gradient diagnostics when asked)."""
        silhouette = multiview_silhouette_loss(
            outputs.verts_cam, self.faces, samples, outputs.counts, self.loss_cfg, iteration
        )
        stats = dict(silhouette.stats)
        if diagnostics:
            stats.update(_gradient_norms(outputs.shape.verts, {"dist": silhouette.dist, "xent": silhouette.xent}))
            # the layout's own signal: the input view's silhouette does not depend on z and rho, so
            # without l_dist only the other-view pairs l_xent reaches move them
            stats.update(_gradient_norms(outputs.layout.z, {"z": silhouette.l3d}))
            stats.update(_gradient_norms(outputs.layout.rho, {"rho": silhouette.l3d}))
            if stats["grad_xent"] > 0:  # no ratio while the gate keeps every pair out of l_xent
                stats["grad_ratio"] = stats["grad_dist"] / stats["grad_xent"]
        return silhouette.l3d, stats

    # ------------------------------------------------------------------ inference
    @torch.no_grad()
    def predict(self, frames: Sequence[FrameData], mode: str = "gt_boxes") -> list[ObjectPredictions]:
        """Shapes and layouts for each input view.

        ``gt_boxes``: objects are the frame's annotated instances (``boxes``, ``labels``),
        scores 1 and ``instance_ids`` from the frame. ``detections``: the detector's output
        after score threshold and NMS; ``instance_ids`` are -1 (the evaluator matches).
        """
        if mode not in MODES:
            raise ValueError(f"predict: mode must be one of {MODES}, got {mode!r}")
        was_training = self.training
        self.eval()
        try:
            image_list, features = self._backbone(frames)
            device = self.pixel_mean.device
            if mode == "gt_boxes":
                boxes = [f.boxes.to(device) for f in frames]
                labels = [f.labels.to(device) for f in frames]
                scores = [torch.ones(len(b), device=device) for b in boxes]
                ids = [f.instance_ids.to(device) for f in frames]
            else:
                detections = self.detector.detect_boxes(image_list, features)
                boxes = [d.pred_boxes for d in detections]
                labels = [d.pred_classes for d in detections]
                scores = [d.scores for d in detections]
                ids = [torch.full((len(d),), -1, dtype=torch.int64, device=device) for d in detections]
            outputs = self.objects(features, boxes, labels, [f.K.to(device) for f in frames])
        finally:
            self.train(was_training)
        return _split_predictions(outputs, boxes, labels, scores, ids, self.faces)


def _split_predictions(
    outputs: ObjectOutputs,
    boxes: list[Tensor],
    labels: list[Tensor],
    scores: list[Tensor],
    ids: list[Tensor],
    faces: Tensor,
) -> list[ObjectPredictions]:
    z, rho, verts = (t.split(outputs.counts) for t in (outputs.layout.z, outputs.layout.rho, outputs.verts_cam))
    return [
        ObjectPredictions(
            boxes=b.float(),
            labels=l.long(),
            scores=s.float(),
            z=zi.float(),
            rho=ri.float(),
            verts=v.float(),
            faces=faces,
            instance_ids=i.long(),
        )
        for b, l, s, zi, ri, v, i in zip(boxes, labels, scores, z, rho, verts, ids, strict=True)
    ]


def _gradient_norms(at: Tensor, terms: dict[str, Tensor]) -> dict[str, Tensor]:
    """``grad_<name>``: norm of each term's gradient w.r.t. ``at`` (the graph is kept)."""
    norms = {}
    for name, term in terms.items():
        if not term.requires_grad:
            norms[f"grad_{name}"] = torch.zeros((), device=at.device)
            continue
        (grad,) = torch.autograd.grad(term, at, retain_graph=True, allow_unused=True)
        norms[f"grad_{name}"] = torch.zeros((), device=at.device) if grad is None else grad.detach().norm()
    return norms
