"""Detector configuration as nested dataclasses (defaults: Mask R-CNN R50-FPN, detectron2 recipe; a plain-R50 preset)."""

from __future__ import annotations

from dataclasses import dataclass, field

from ..backbone import BackboneConfig, ResNetConfig


@dataclass
class AnchorConfig:
    sizes: tuple[tuple[float, ...], ...] = ((32,), (64,), (128,), (256,), (512,))  # one tuple per RPN level
    aspect_ratios: tuple[float, ...] = (0.5, 1.0, 2.0)  # height / width
    offset: float = 0.0


@dataclass
class RPNConfig:
    in_features: tuple[str, ...] = ("p2", "p3", "p4", "p5", "p6")
    anchors: AnchorConfig = field(default_factory=AnchorConfig)
    iou_thresholds: tuple[float, float] = (0.3, 0.7)  # below: background, above: foreground
    batch_size_per_image: int = 256
    positive_fraction: float = 0.5
    bbox_reg_weights: tuple[float, float, float, float] = (1.0, 1.0, 1.0, 1.0)
    smooth_l1_beta: float = 0.0  # 0 gives the L1 loss
    pre_nms_topk_train: int = 2000  # per level
    pre_nms_topk_test: int = 1000  # per level
    post_nms_topk_train: int = 1000  # per image
    post_nms_topk_test: int = 1000  # per image
    nms_thresh: float = 0.7
    min_box_size: float = 0.0
    loss_weight: float = 1.0


@dataclass
class BoxHeadConfig:
    pooler_resolution: int = 7
    pooler_sampling_ratio: int = 0  # <= 0: adaptive
    num_fc: int = 2
    fc_dim: int = 1024
    bbox_reg_weights: tuple[float, float, float, float] = (10.0, 10.0, 5.0, 5.0)
    smooth_l1_beta: float = 0.0
    loss_weight: float = 1.0


@dataclass
class MaskHeadConfig:
    enabled: bool = True
    pooler_resolution: int = 14  # masks are predicted at twice this (28x28)
    pooler_sampling_ratio: int = 0
    num_conv: int = 4
    conv_dim: int = 256
    loss_weight: float = 1.0


@dataclass
class PointRendConfig:
    """PointRend's mask branch (Kirillov et al. 2020) as detectron2's ``pointrend_rcnn_R_50_FPN`` builds it.

    A coarse head predicts ``coarse_resolution``-square logits per class from a regular grid of
    features; the point head then re-predicts single points from fine features plus the coarse
    logits. Inference starts from a regular grid and, ``subdivision_steps`` times, doubles the
    resolution and re-predicts the ``subdivision_num_points`` most uncertain cells (7 -> 224).
    """

    in_feature: str = "p2"  # both heads read the finest FPN level
    pooler_resolution: int = 14  # the coarse head's regular grid of samples per box
    conv_dim: int = 256
    num_fc: int = 2
    fc_dim: int = 1024
    coarse_resolution: int = 7
    point_num_fc: int = 3
    point_fc_dim: int = 256
    train_num_points: int = 14 * 14
    oversample_ratio: int = 3  # training: candidates per point (k in the paper)
    importance_sample_ratio: float = 0.75  # training: share of points picked by uncertainty (beta)
    subdivision_steps: int = 5
    subdivision_num_points: int = 28 * 28


@dataclass
class ROIHeadsConfig:
    name: str = "standard"  # key in ROI_HEADS: "standard" (Mask R-CNN) | "point_rend"
    in_features: tuple[str, ...] = ("p2", "p3", "p4", "p5")
    batch_size_per_image: int = 512
    positive_fraction: float = 0.25
    iou_threshold: float = 0.5  # proposals at or above it are foreground
    proposal_append_gt: bool = True
    canonical_box_size: float = 224.0  # a box of this size is pooled from canonical_level (FPN paper, eq. 1)
    canonical_level: int = 4
    score_thresh_test: float = 0.05
    nms_thresh_test: float = 0.5
    detections_per_image: int = 100
    mask_threshold: float = 0.5  # pasted mask probabilities at or above it are foreground
    box_head: BoxHeadConfig = field(default_factory=BoxHeadConfig)
    mask_head: MaskHeadConfig = field(default_factory=MaskHeadConfig)
    point_rend: PointRendConfig = field(default_factory=PointRendConfig)  # the mask branch of "point_rend"


@dataclass
class DetectorConfig:
    backbone: BackboneConfig = field(default_factory=BackboneConfig)
    rpn: RPNConfig = field(default_factory=RPNConfig)
    roi_heads: ROIHeadsConfig = field(default_factory=ROIHeadsConfig)

    @classmethod
    def r50(cls) -> "DetectorConfig":
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
    def point_rend(cls) -> "DetectorConfig":
        """PointRend R50-FPN (detectron2's ``pointrend_rcnn_R_50_FPN_3x_coco``): Mask R-CNN with PointRend's mask branch."""
        return cls(roi_heads=ROIHeadsConfig(name="point_rend"))

    @classmethod
    def tiny(cls) -> "DetectorConfig":
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
