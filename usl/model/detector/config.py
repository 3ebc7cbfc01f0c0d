"""Detector configuration as nested dataclasses (defaults: Mask R-CNN R50-FPN, detectron2 recipe; a plain-R50 preset)."""

from __future__ import annotations

from dataclasses import dataclass, field

from ..backbone import BackboneConfig, ResNetConfig


@dataclass
class AnchorConfig:
    # pixels, one tuple per RPN level: scale them with the objects in the images
    sizes: tuple[tuple[float, ...], ...] = ((32,), (64,), (128,), (256,), (512,))
    aspect_ratios: tuple[float, ...] = (0.5, 1.0, 2.0)  # height / width: widen it for long thin objects


@dataclass
class RPNConfig:
    in_features: tuple[str, ...] = ("p2", "p3", "p4", "p5", "p6")  # maps the RPN proposes on, one per anchors.sizes
    anchors: AnchorConfig = field(default_factory=AnchorConfig)
    batch_size_per_image: int = 256  # anchors sampled per image for the RPN losses (fewer: faster)
    pre_nms_topk_train: int = 2000  # proposals kept per level before NMS, in training (fewer: faster)
    pre_nms_topk_test: int = 1000  # the same at inference (fewer: faster)
    post_nms_topk_train: int = 1000  # proposals kept per image after NMS, in training (fewer: faster, for few objects)
    post_nms_topk_test: int = 1000  # the same at inference: more than an image's objects
    nms_thresh: float = 0.7  # proposals overlapping a better one by more IoU are dropped (higher: crowded objects)


@dataclass
class BoxHeadConfig:
    fc_dim: int = 1024  # width of the box head's two FC layers (smaller: faster)


@dataclass
class MaskHeadConfig:
    num_conv: int = 4  # 3 x 3 convs before the 2x deconv to 28 x 28 masks (fewer: faster)
    conv_dim: int = 256  # their width (smaller: faster)


@dataclass
class ROIHeadsConfig:
    name: str = "standard"  # mask branch, a key in ROI_HEADS: "standard" (Mask R-CNN) | "point_rend" (224² masks)
    in_features: tuple[str, ...] = ("p2", "p3", "p4", "p5")  # backbone maps the RoI heads pool from, by box size
    batch_size_per_image: int = 512  # proposals sampled per image for the box and mask losses (fewer: faster)
    canonical_box_size: float = 224.0  # boxes this big pool from level 4 (FPN eq. 1): scale it with the images
    score_thresh_test: float = 0.05  # detections scoring below this are dropped (higher: fewer false ones)
    nms_thresh_test: float = 0.5  # per-class NMS IoU of the detections (higher: keeps overlapping objects)
    detections_per_image: int = 100  # at most this many detections per image: more than a scene's objects
    mask_threshold: float = 0.5  # pasted mask probabilities at or above it are foreground (higher: tighter masks)
    box_head: BoxHeadConfig = field(default_factory=BoxHeadConfig)
    mask_head: MaskHeadConfig = field(default_factory=MaskHeadConfig)


@dataclass
class DetectorConfig:
    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    rpn: RPNConfig = field(default_factory=RPNConfig)
    roi_heads: ROIHeadsConfig = field(default_factory=ROIHeadsConfig)

    @classmethod
    def r50(cls) -> DetectorConfig:
        """A plain ResNet-50 (no FPN) as Mesh R-CNN's ShapeNet model trains it, under a C4 detector.

        The backbone exposes res2..res5 for the shape head and, like that model's torchvision
        ResNet, keeps BatchNorm with batch statistics and freezes nothing. The RPN runs on res4 with
        all five anchor sizes at its stride 16 and the RoI heads pool res4, with the RPN top-k of
        detectron2's ``Base-RCNN-C4``. One deviation from R50-C4: the box and mask heads are this
        package's FPN-style heads (2 x FC 1024, 4 x conv 256) on the pooled res4 features, not
        detectron2's res5 RoI head (a second copy of the last stage, run per RoI).
        """
        return cls(
            backbone=BackboneConfig(name="resnet", resnet=ResNetConfig(norm="BN", freeze_at=0)),
            rpn=RPNConfig(
                in_features=("res4",),
                anchors=AnchorConfig(sizes=((32, 64, 128, 256, 512),)),
                pre_nms_topk_train=12000,
                pre_nms_topk_test=6000,
                post_nms_topk_train=2000,
                post_nms_topk_test=1000,
            ),
            roi_heads=ROIHeadsConfig(in_features=("res4",)),
        )

    @classmethod
    def tiny(cls) -> DetectorConfig:
        """A few-hundred-K-parameter Mask R-CNN for ~128x128 images, trainable on a CPU in seconds."""
        return cls(
            backbone=BackboneConfig.tiny(),
            rpn=RPNConfig(
                anchors=AnchorConfig(sizes=((8,), (16,), (32,), (64,), (128,))),
                batch_size_per_image=128,
                pre_nms_topk_train=100,
                pre_nms_topk_test=100,
                post_nms_topk_train=64,
                post_nms_topk_test=50,
            ),
            roi_heads=ROIHeadsConfig(
                batch_size_per_image=64,
                canonical_box_size=56.0,
                detections_per_image=20,
                box_head=BoxHeadConfig(fc_dim=128),
                mask_head=MaskHeadConfig(num_conv=2, conv_dim=32),
            ),
        )
