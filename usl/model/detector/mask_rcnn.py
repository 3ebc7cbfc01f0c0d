"""Mask R-CNN: backbone -> RPN -> RoI heads, with dict-based inputs and outputs."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn

from ..backbone import ShapeSpec, build_backbone
from ..backbone.resnet import channels_last_on
from .config import DetectorConfig
from .roi_heads import build_roi_heads
from .rpn import RPN
from .structures import ImageList, Instances

Tensor = torch.Tensor


class InvalidTargetError(ValueError):
    """A training target dict does not follow the documented layout."""


class MaskRCNN(nn.Module):
    """Mask R-CNN detector for ``num_classes`` categories (labels ``0 .. num_classes - 1``).

    A model built on it shares its backbone through :meth:`preprocess`, :meth:`features` and
    :meth:`feature_shapes` (FPN ``p2..p6``, or a plain ResNet's ``res2..res5``) and runs its heads on
    those features through :meth:`losses` (training) and :meth:`detect_boxes` (inference). The parts
    (``backbone``, ``proposal_generator``: the RPN, ``roi_heads``) keep their attribute names: they
    are the state-dict keys the pretrained layouts map onto.
    """

    def __init__(self, num_classes: int, cfg: DetectorConfig | None = None):
        super().__init__()
        if num_classes < 1:
            raise ValueError(f"num_classes must be positive, got {num_classes}")
        self.cfg = cfg or DetectorConfig()
        self.num_classes = num_classes
        self.backbone = build_backbone(self.cfg.backbone)
        shapes = self.backbone.output_shape()
        self.proposal_generator = RPN(self.cfg.rpn, shapes)
        self.roi_heads = build_roi_heads(self.cfg.roi_heads, num_classes, shapes)

    def lay_out_weights_like_features(self, device: torch.device) -> None:
        """Hold the weights of the convolutions that read the feature maps (the backbone's and the RPN
        head's) in the maps' layout on ``device``: channels-last on the CPU.

        A convolution's weight gradient comes out in its input's layout. In the weight's own layout
        autograd keeps it as it is (in another, it copies it into the weight's layout every step),
        and DDP's gradient buckets, laid out like the weights, take it stride for stride (otherwise
        DDP warns "Grad strides do not match bucket view strides"). Call it before wrapping in DDP."""
        if channels_last_on(device):
            self.backbone.to(memory_format=torch.channels_last)
            self.proposal_generator.to(memory_format=torch.channels_last)

    def preprocess(self, images: Tensor, image_sizes: Sequence[tuple[int, int]] | None = None) -> ImageList:
        """Pad normalised images (N, 3, H, W) so every feature map aligns."""
        return ImageList.from_tensor(images, image_sizes, self.backbone.size_divisibility)

    def forward(
        self,
        images: Tensor,
        image_sizes: Sequence[tuple[int, int]] | None = None,
        targets: Sequence[dict[str, Tensor]] | None = None,
    ) -> dict[str, Tensor] | list[dict[str, Tensor]]:
        """Training: a dict of named losses. Eval: per image ``{boxes, scores, labels, masks}``.

        Args:
            images: normalised images (N, 3, H, W); image ``i`` occupies ``[:h_i, :w_i]``.
            image_sizes: ``(h_i, w_i)`` per image; default: all ``(H, W)``.
            targets: training only; per image ``boxes`` (K, 4) xyxy pixels, ``labels`` (K,)
                long in ``[0, num_classes)``, ``masks`` (K, h_i, w_i) bool (if the mask head is on).
        Eval boxes are in input pixels; ``masks`` are bool (K, h_i, w_i).
        """
        image_list = self.preprocess(images, image_sizes)
        if self.training:
            if targets is None:
                raise ValueError("MaskRCNN needs targets in training mode")
            return self.losses(image_list, self.features(image_list), targets)
        features = self.features(image_list)
        detections = self.roi_heads.forward_mask(features, self.detect_boxes(image_list, features))
        return [self.instances_to_dict(d) for d in detections]

    def feature_shapes(self) -> dict[str, ShapeSpec]:
        """Channels and stride of each of :meth:`features`' maps, by name."""
        return self.backbone.output_shape()

    def features(self, image_list: ImageList) -> dict[str, Tensor]:
        """The backbone's feature maps of :meth:`preprocess`'s images."""
        return self.backbone(image_list.tensor)

    def losses(
        self, image_list: ImageList, features: dict[str, Tensor], targets: Sequence[dict[str, Tensor]]
    ) -> dict[str, Tensor]:
        """Training: the RPN's and RoI heads' losses against ``targets`` (laid out as :meth:`forward`'s)."""
        gt = self.targets_to_instances(targets, image_list.image_sizes)
        proposals, rpn_losses = self.proposal_generator(image_list, features, gt)
        _, roi_losses = self.roi_heads(features, proposals, gt)
        return {**rpn_losses, **roi_losses}

    def detect_boxes(self, image_list: ImageList, features: dict[str, Tensor]) -> list[Instances]:
        """Eval: detections per image (``pred_boxes``, ``scores``, ``pred_classes``) after score
        threshold, per-class NMS and top-k, without masks."""
        if self.training:
            raise RuntimeError("MaskRCNN.detect_boxes needs eval mode")
        proposals, _ = self.proposal_generator(image_list, features)
        return self.roi_heads.forward_box(features, proposals)

    @torch.no_grad()
    def detect(self, images: Tensor, image_sizes: Sequence[tuple[int, int]] | None = None) -> list[Instances]:
        """Eval detections per image with box-relative mask probabilities ``mask_probs`` (R, M, M), not pasted.

        For callers that detect in resized images and paste the masks at another size.
        """
        if self.training:
            raise RuntimeError("MaskRCNN.detect needs eval mode")
        image_list = self.preprocess(images, image_sizes)
        features = self.features(image_list)
        detections = self.detect_boxes(image_list, features)
        probabilities = self.roi_heads.mask_probabilities(features, detections)
        for instances, probs in zip(detections, probabilities.split([len(d) for d in detections]), strict=True):
            instances.mask_probs = probs
        return detections

    def targets_to_instances(
        self, targets: Sequence[dict[str, Tensor]], image_sizes: Sequence[tuple[int, int]]
    ) -> list[Instances]:
        """Validate target dicts and convert them to Instances (``gt_boxes``, ``gt_classes``, ``gt_masks``)."""
        if len(targets) != len(image_sizes):
            raise InvalidTargetError(f"{len(targets)} targets for {len(image_sizes)} images")
        device = next(self.parameters()).device
        converted = []
        for index, (target, size) in enumerate(zip(targets, image_sizes, strict=True)):
            boxes, labels = target.get("boxes"), target.get("labels")
            if boxes is None or labels is None:
                raise InvalidTargetError(f"target {index} needs 'boxes' and 'labels', has {sorted(target)}")
            if boxes.dim() != 2 or boxes.shape[1] != 4 or labels.shape != boxes.shape[:1]:
                raise InvalidTargetError(
                    f"target {index}: boxes must be (K, 4) and labels (K,), "
                    f"got {tuple(boxes.shape)} and {tuple(labels.shape)}"
                )
            fields = {"gt_boxes": boxes.to(device, torch.float32), "gt_classes": labels.to(device, torch.long)}
            masks = target.get("masks")
            if masks is None or tuple(masks.shape) != (len(boxes), *size):
                shape = None if masks is None else tuple(masks.shape)
                raise InvalidTargetError(
                    f"target {index}: masks must be (K, h, w) = {(len(boxes), *size)}, got {shape}"
                )
            fields["gt_masks"] = masks.to(device, torch.bool)
            converted.append(Instances(size, **fields))
        self._check_labels([instances.gt_classes for instances in converted])
        return converted

    def _check_labels(self, labels: list[Tensor]) -> None:
        """Every image's labels in [0, num_classes), read back once for the whole batch."""
        if not any(len(image_labels) for image_labels in labels):
            return
        flat = torch.cat(labels)
        image = torch.cat([torch.full_like(image_labels, i) for i, image_labels in enumerate(labels)])
        bad = (flat < 0) | (flat >= self.num_classes)
        first = int(torch.where(bad, image, len(labels)).min())
        if first < len(labels):
            raise InvalidTargetError(
                f"target {first}: labels must lie in [0, {self.num_classes}), got {labels[first].tolist()}"
            )

    @staticmethod
    def instances_to_dict(detections: Instances) -> dict[str, Tensor]:
        output = {"boxes": detections.pred_boxes, "scores": detections.scores, "labels": detections.pred_classes}
        if detections.has("pred_masks"):
            output["masks"] = detections.pred_masks
        return output
