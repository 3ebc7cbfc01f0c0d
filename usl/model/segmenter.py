"""A COCO instance segmenter from pretrained weights: detectron2's PointRend or Mask R-CNN, torchvision's Mask R-CNN.

:class:`InstanceSegmenter` reproduces detectron2's ``DefaultPredictor``: resize the shortest edge to
``min_size`` (longest at most ``max_size``) with PIL's bilinear filter, detect in the resized image,
then scale the boxes back, clip them, drop empty ones and paste each mask at the original size. The
weights file decides the network (:func:`detector_for_weights`); category ids are COCO's.

A batch runs one forward pass per resized size, so no image is padded beyond its own size and a
batch gives exactly what one image at a time gives (padding to a larger image's size, as detectron2
batches, puts anchors over the padding and changes the proposals).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from data_specs import coco_category_ids
from usl.utils.transfer import constant, to_device

from .backbone import IMAGENET_MEAN, IMAGENET_STD, BackboneConfig, ResNetConfig
from .detector import DetectorConfig, MaskRCNN, ROIHeadsConfig
from .detector.mask_head import paste_masks_in_image
from .ops import clip_boxes, nonempty_boxes
from .pretrained import WeightsError, init_detector, read_weights
from .pretrained.layouts import DETECTRON2_RCNN, TORCHVISION_MASK_RCNN

Tensor = torch.Tensor
# torchvision's COCO models keep a slot per id 1..90 (the gaps never fire): class k is id k + 1.
TORCHVISION_COCO_IDS = tuple(range(1, 91))


@dataclass(frozen=True)
class SegmenterConfig:
    """detectron2's inference defaults (``INPUT.{MIN,MAX}_SIZE_TEST``, ``MODEL.ROI_HEADS.*_TEST``)."""

    min_size: int = 800  # shortest edge after resizing
    max_size: int = 1333  # longest edge at most
    score_threshold: float = 0.05
    max_detections: int = 100  # per image
    nms_threshold: float = 0.5
    mask_threshold: float = 0.5


@dataclass
class Segmentation:
    """Instances of one image in its original pixels, best first."""

    boxes: np.ndarray  # (K, 4) float32 xyxy
    scores: np.ndarray  # (K,) float32
    category_ids: np.ndarray  # (K,) int64 COCO ids
    masks: np.ndarray  # (K, H, W) bool

    def __len__(self) -> int:
        return len(self.scores)


def detector_for_weights(path: str | Path, cfg: SegmenterConfig) -> tuple[MaskRCNN, tuple[int, ...]]:
    """The COCO detector a weights file holds, loaded, in eval mode, with its class -> COCO id table.

    detectron2 ``.pkl``: PointRend if it has PointRend's heads, else Mask R-CNN (80 classes);
    torchvision ``.pth``: ``maskrcnn_resnet50_fpn`` (91 slots with background).
    """
    weights = read_weights(path)
    point_rend = any(".point_head." in k or "mask_point_head." in k for k in weights.tensors)
    if weights.format == "detectron2" and DETECTRON2_RCNN.signature in weights.tensors:
        classes, stride_in_1x1, category_ids = 80, True, coco_category_ids()
    elif weights.format == "torchvision" and TORCHVISION_MASK_RCNN.signature in weights.tensors:
        classes, stride_in_1x1, category_ids = 90, False, TORCHVISION_COCO_IDS
    else:
        raise WeightsError(
            f"weights file {weights.path}: not a COCO instance segmenter (detectron2 PointRend or Mask R-CNN .pkl, "
            "torchvision maskrcnn_resnet50_fpn .pth)"
        )
    scores = weights.tensors.get("roi_heads.box_predictor.cls_score.weight")  # both layouts name it so
    if scores is not None and scores.shape[0] != classes + 1:
        raise WeightsError(f"weights file {weights.path}: {scores.shape[0] - 1} classes, a COCO model has {classes}")
    roi_heads = ROIHeadsConfig(
        name="point_rend" if point_rend else "standard",
        score_thresh_test=cfg.score_threshold,
        nms_thresh_test=cfg.nms_threshold,
        detections_per_image=cfg.max_detections,
        mask_threshold=cfg.mask_threshold,
    )
    backbone = BackboneConfig(resnet=ResNetConfig(stride_in_1x1=stride_in_1x1))
    detector = MaskRCNN(classes, DetectorConfig(backbone=backbone, roi_heads=roi_heads))
    report = init_detector(detector, weights)
    if report.reinitialised or report.kept.keys() - {"backbone.bottom_up.fc"}:
        raise WeightsError(f"weights file {weights.path} does not cover the detector: " + "; ".join(report.lines()))
    return detector.eval(), category_ids


def resized_shape(height: int, width: int, min_size: int, max_size: int) -> tuple[int, int]:
    """detectron2's ``ResizeShortestEdge.get_output_shape`` (rounding included)."""
    scale = min_size / min(height, width)
    new_h, new_w = (min_size, scale * width) if height < width else (scale * height, min_size)
    if max(new_h, new_w) > max_size:
        scale = max_size / max(new_h, new_w)
        new_h, new_w = new_h * scale, new_w * scale
    return int(new_h + 0.5), int(new_w + 0.5)


class InstanceSegmenter:
    """``segmenter(images)``: RGB uint8 (H, W, 3) arrays -> one :class:`Segmentation` each."""

    def __init__(self, detector: MaskRCNN, category_ids: Sequence[int], cfg: SegmenterConfig):
        if len(category_ids) != detector.num_classes:
            raise ValueError(f"{len(category_ids)} category ids for {detector.num_classes} classes")
        self.detector = detector.eval()
        self.category_ids = torch.tensor(category_ids, dtype=torch.long)
        self.cfg = cfg

    @classmethod
    def from_weights(
        cls, path: str | Path, cfg: SegmenterConfig | None = None, device: str | torch.device = "cpu"
    ) -> InstanceSegmenter:
        cfg = cfg or SegmenterConfig()
        detector, category_ids = detector_for_weights(path, cfg)
        return cls(detector.to(device), category_ids, cfg)

    @property
    def device(self) -> torch.device:
        return next(self.detector.parameters()).device

    def preprocess(self, image: np.ndarray) -> Tensor:
        """Resized (PIL bilinear, as detectron2) and normalised (3, h, w) float tensor on the device."""
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"images must be RGB uint8 (H, W, 3), got {image.dtype} {image.shape}")
        height, width = resized_shape(image.shape[0], image.shape[1], self.cfg.min_size, self.cfg.max_size)
        resized = np.asarray(Image.fromarray(image).resize((width, height), Image.BILINEAR))
        pixels = to_device(np.array(resized), self.device).permute(2, 0, 1).float()
        mean = constant(IMAGENET_MEAN, pixels.dtype, pixels.device)[:, None, None]
        std = constant(IMAGENET_STD, pixels.dtype, pixels.device)[:, None, None]
        return (pixels / 255.0 - mean) / std

    @torch.no_grad()
    def __call__(self, images: Sequence[np.ndarray]) -> list[Segmentation]:
        """One forward pass per resized size among ``images``: no image is padded beyond its own size."""
        inputs = [self.preprocess(image) for image in images]
        groups: dict[tuple[int, int], list[int]] = {}
        for index, x in enumerate(inputs):
            groups.setdefault(tuple(x.shape[1:]), []).append(index)
        results: list[Segmentation | None] = [None] * len(images)
        for size, indices in groups.items():
            detections = self.detector.detect(torch.stack([inputs[i] for i in indices]), [size] * len(indices))
            for index, found in zip(indices, detections, strict=True):
                results[index] = self._postprocess(found, images[index].shape[:2])
        return results

    def _postprocess(self, detections, original_size: tuple[int, int]) -> Segmentation:
        """detectron2's ``detector_postprocess``: boxes to the original pixels, masks pasted there."""
        (height, width), (resized_h, resized_w) = original_size, detections.image_size
        scale = detections.pred_boxes.new_tensor([width / resized_w, height / resized_h] * 2)
        boxes = clip_boxes(detections.pred_boxes * scale, (height, width))
        keep = nonempty_boxes(boxes)
        boxes, probabilities = boxes[keep], detections.mask_probs[keep]
        masks = paste_masks_in_image(probabilities, boxes, (height, width), self.cfg.mask_threshold)
        classes = detections.pred_classes[keep].cpu()
        return Segmentation(
            boxes=boxes.cpu().numpy().astype(np.float32),
            scores=detections.scores[keep].cpu().numpy().astype(np.float32),
            category_ids=self.category_ids[classes].numpy(),
            masks=masks.cpu().numpy(),
        )
