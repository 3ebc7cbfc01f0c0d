"""PointRend's mask branch: sampling, the heads, subdivision, training, and detectron2's checkpoints."""

from __future__ import annotations

import dataclasses
import pickle

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from tests.model.detection_oracles import _bilinear
from tests.model.detection_scenes import make_dataset
from tests.model.detectron2_fixtures import CHECKPOINT_KEYS, MASK_RCNN, POINTREND
from usl.model.detector import DetectorConfig, MaskRCNN
from usl.model.detector.point_rend import (
    PointHead,
    PointRendSettings,
    bilinear_mask_values,
    most_uncertain_cells,
    regular_grid,
    sample_box_points,
)
from usl.model.detector.roi_heads import PointRendROIHeads
from usl.model.pretrained import WeightsError, init_detector
from usl.model.segmenter import SegmenterConfig, detector_for_weights


def small_settings(**changes) -> PointRendSettings:
    return dataclasses.replace(PointRendSettings(), **{"conv_dim": 32, "fc_dim": 32, "point_fc_dim": 16, **changes})


def tiny_point_rend(monkeypatch, **changes) -> DetectorConfig:
    """The tiny detector with PointRend's mask branch, its heads narrowed (the layout stays detectron2's)."""
    monkeypatch.setattr(PointRendROIHeads, "settings", small_settings(**changes))
    cfg = DetectorConfig.tiny()
    cfg.roi_heads.name = "point_rend"
    return cfg


def test_regular_grid_is_the_cell_centres_row_major():
    grid = regular_grid(4, 2, torch.device("cpu"))
    assert grid.shape == (2, 16, 2)
    # affine_grid without corner alignment spans the cell centres of [-1, 1]; map to [0, 1]
    reference = F.affine_grid(torch.tensor([[[1.0, 0, 0], [0, 1.0, 0]]]), [1, 1, 4, 4], align_corners=False)
    torch.testing.assert_close(grid[1], (reference.view(-1, 2) + 1) / 2)


def test_box_points_are_bilinear_samples_of_the_right_image():
    generator = torch.Generator().manual_seed(0)
    stride = 4
    feature = torch.randn(2, 3, 10, 12, generator=generator)
    boxes = [torch.tensor([[3.0, 5.0, 30.0, 20.0]]), torch.tensor([[0.0, 0.0, 48.0, 40.0], [10.0, 2.0, 11.0, 39.0]])]
    points = torch.rand(3, 5, 2, generator=generator)
    sampled = sample_box_points(feature, stride, boxes, points)
    owners = [0, 1, 1]
    for row, box in enumerate(torch.cat(boxes)):
        for p in range(points.shape[1]):
            x = float(box[0] + points[row, p, 0] * (box[2] - box[0])) / stride - 0.5
            y = float(box[1] + points[row, p, 1] * (box[3] - box[1])) / stride - 0.5
            expected = _bilinear_zero_padded(feature[owners[row]], y, x)
            torch.testing.assert_close(sampled[row, :, p], expected, atol=1e-5, rtol=1e-5)


def _bilinear_zero_padded(feature, y, x):
    """Bilinear interpolation with zeros outside the map (grid_sample's padding), one point."""
    padded = F.pad(feature, (1, 1, 1, 1))
    return _bilinear(padded, y + 1, x + 1)


def test_mask_values_follow_grid_sample_of_each_rows_mask():
    generator = torch.Generator().manual_seed(1)
    masks = torch.rand(3, 9, 11, generator=generator) > 0.5
    which = torch.tensor([2, 0, 2, 1])
    points = torch.rand(4, 20, 2, generator=generator) * torch.tensor([13.0, 11.0]) - 1  # some outside
    expected = F.grid_sample(
        masks[which, None].float(), (points / torch.tensor([11.0, 9.0]) * 2 - 1)[:, :, None], align_corners=False
    )[:, 0, :, 0]
    torch.testing.assert_close(bilinear_mask_values(masks, which, points), expected)


def test_most_uncertain_cells_pick_logits_nearest_zero():
    logits = torch.tensor([[[3.0, -0.1], [0.5, -2.0]], [[0.0, 1.0], [-1.0, 0.2]]])
    index, centres = most_uncertain_cells(logits, 2)
    assert index.tolist() == [[1, 2], [0, 3]]
    torch.testing.assert_close(centres[0], torch.tensor([[0.75, 0.25], [0.25, 0.75]]))
    assert most_uncertain_cells(logits, 10)[0].shape == (2, 4)  # never more than the grid has


def test_point_head_for_one_class_is_that_row_of_all_classes():
    torch.manual_seed(0)
    head = PointHead(8, 5, small_settings())
    torch.nn.init.normal_(head.predictor.weight)
    fine, coarse = torch.randn(4, 8, 6), torch.randn(4, 5, 6)
    classes = torch.tensor([3, 0, 4, 3])
    every = head(fine, coarse)
    assert every.shape == (4, 5, 6)
    torch.testing.assert_close(head(fine, coarse, classes), every[torch.arange(4), classes])


def test_subdivision_starts_where_every_cell_would_be_refined_and_ends_at_224(monkeypatch):
    detector = MaskRCNN(3, tiny_point_rend(monkeypatch))
    head = detector.roi_heads.mask_head
    assert (head.start_resolution, head.steps, head.output_resolution) == (28, 3, 224)


def test_subdivision_refines_only_the_most_uncertain_cells(monkeypatch):
    """Step by step: upsample, then exactly the chosen cells take the point head's prediction."""
    torch.manual_seed(0)
    detector = MaskRCNN(3, tiny_point_rend(monkeypatch, subdivision_steps=3, subdivision_num_points=50)).eval()
    head = detector.roi_heads.mask_head
    assert (head.start_resolution, head.steps) == (7, 3)
    torch.nn.init.normal_(head.point_head.predictor.weight, std=1.0)
    images = torch.randn(2, 3, 64, 64)
    features = detector.backbone(images)
    boxes = [torch.tensor([[4.0, 6.0, 40.0, 50.0]]), torch.tensor([[10.0, 10.0, 60.0, 30.0], [0.0, 0.0, 64, 64]])]
    classes = torch.tensor([0, 2, 1])
    with torch.no_grad():
        result = head.predict(features, boxes, classes)
        feature = features["p2"]
        coarse = head.coarse_logits(feature, boxes)
        logits = head.point_logits(feature, boxes, coarse, regular_grid(7, 3, feature.device), classes).view(3, 7, 7)
        for _ in range(3):
            logits = F.interpolate(logits[:, None], scale_factor=2, mode="bilinear", align_corners=False)[:, 0]
            index, points = most_uncertain_cells(logits, 50)
            dense = head.point_logits(feature, boxes, coarse, points, classes)
            logits = logits.flatten(1).scatter(1, index, dense).view_as(logits)
    assert result.shape == (3, 56, 56)
    torch.testing.assert_close(result, logits)
    # one image at a time gives the same masks (no mixing across images in the batch)
    with torch.no_grad():
        alone = head.predict({k: v[1:] for k, v in features.items()}, boxes[1:], classes[1:])
        empty = head.predict(features, [boxes[0], torch.zeros((0, 4))], classes[:1])
        nothing = head.predict(features, [torch.zeros((0, 4)), torch.zeros((0, 4))], classes[:0])
    torch.testing.assert_close(alone, result[1:], atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(empty, result[:1], atol=1e-5, rtol=1e-5)  # an image without detections
    assert nothing.shape == (0, 56, 56)


def test_point_rend_trains_both_heads_and_predicts_full_size_masks(monkeypatch):
    images, targets = make_dataset(2, seed=3)
    detector = MaskRCNN(2, tiny_point_rend(monkeypatch)).train()
    losses = detector(images, targets=targets)
    assert {"loss_mask", "loss_mask_point"} <= losses.keys()
    sum(losses.values()).backward()
    head = detector.roi_heads.mask_head
    assert head.coarse_head.predictor.weight.grad.abs().sum() > 0
    assert head.point_head.predictor.weight.grad.abs().sum() > 0
    with torch.no_grad():
        outputs = detector.eval()(images)
    assert all(o["masks"].shape[1:] == images.shape[2:] for o in outputs)


def write_pickle(path, arrays):
    with open(path, "wb") as stream:
        pickle.dump({"model": arrays, "__author__": "test"}, stream)


def random_arrays(model: str, rename=lambda key: key) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    return {rename(k): rng.standard_normal(shape).astype(np.float32) for k, shape in CHECKPOINT_KEYS[model].items()}


# detectron2 key (after the model zoo's old names are read as the new ones) -> our key
POINTREND_TARGETS = {
    "roi_heads.mask_head.coarse_head.reduce_spatial_dim_conv": "roi_heads.mask_head.coarse_head.conv",
    "roi_heads.mask_head.coarse_head.fc1": "roi_heads.mask_head.coarse_head.fcs.0",
    "roi_heads.mask_head.coarse_head.fc2": "roi_heads.mask_head.coarse_head.fcs.1",
    "roi_heads.mask_head.coarse_head.prediction": "roi_heads.mask_head.coarse_head.predictor",
    "roi_heads.mask_head.point_head.fc1": "roi_heads.mask_head.point_head.fcs.0",
    "roi_heads.mask_head.point_head.fc2": "roi_heads.mask_head.point_head.fcs.1",
    "roi_heads.mask_head.point_head.fc3": "roi_heads.mask_head.point_head.fcs.2",
    "roi_heads.mask_head.point_head.predictor": "roi_heads.mask_head.point_head.predictor",
}


def old_name(key: str) -> str:
    """detectron2's names before the heads moved into the mask head (the 2020 model zoo files)."""
    key = key.replace("mask_head.coarse_head.fc", "mask_coarse_head.coarse_mask_fc")
    return key.replace("mask_head.coarse_head.", "mask_coarse_head.").replace(
        "mask_head.point_head.", "mask_point_head."
    )


@pytest.mark.parametrize("names", ["current", "old"])
def test_detectron2_point_rend_checkpoints_land_everywhere(tmp_path, names):
    rename = old_name if names == "old" else (lambda key: key)
    arrays = random_arrays(POINTREND, rename)
    path = tmp_path / "model_final_edd263.pkl"
    write_pickle(path, arrays)
    detector, category_ids = detector_for_weights(path, SegmenterConfig())
    assert detector.cfg.roi_heads.name == "point_rend" and len(category_ids) == 80
    state = detector.state_dict()
    heads = [k for k in state if k.startswith("roi_heads.mask_head.")]
    assert len(heads) == 2 * len(POINTREND_TARGETS)
    for theirs, ours in POINTREND_TARGETS.items():
        for param in ("weight", "bias"):
            expected = torch.from_numpy(arrays[rename(f"{theirs}.{param}")])
            assert torch.equal(state[f"{ours}.{param}"], expected), theirs


def test_detectron2_mask_rcnn_checkpoint_makes_a_mask_rcnn_segmenter(tmp_path):
    path = tmp_path / "model_final_f10217.pkl"
    arrays = random_arrays(MASK_RCNN)
    write_pickle(path, arrays)
    detector, _ = detector_for_weights(path, SegmenterConfig())
    assert detector.cfg.roi_heads.name == "standard"
    expected = torch.from_numpy(arrays["roi_heads.mask_head.deconv.weight"])
    assert torch.equal(detector.state_dict()["roi_heads.mask_head.deconv.weight"], expected)


def test_point_rend_keys_that_fit_nothing_are_errors_naming_the_key(tmp_path):
    arrays = random_arrays(POINTREND)
    arrays["roi_heads.mask_head.point_head.fc4.weight"] = np.zeros((256, 336, 1), np.float32)
    write_pickle(tmp_path / "extra.pkl", arrays)
    with pytest.raises(WeightsError, match="roi_heads.mask_head.point_head.fc4.weight"):
        detector_for_weights(tmp_path / "extra.pkl", SegmenterConfig())
    arrays = random_arrays(POINTREND)
    arrays["roi_heads.mask_head.coarse_head.fc1.weight"] = np.zeros((1024, 999), np.float32)
    write_pickle(tmp_path / "shape.pkl", arrays)
    with pytest.raises(WeightsError, match="roi_heads.mask_head.coarse_head.fc1.weight"):
        detector_for_weights(tmp_path / "shape.pkl", SegmenterConfig())


def test_point_rend_weights_do_not_load_into_a_mask_rcnn(tmp_path):
    write_pickle(tmp_path / "pointrend.pkl", random_arrays(POINTREND))
    cfg = DetectorConfig()
    cfg.backbone.resnet.stride_in_1x1 = True
    with pytest.raises(WeightsError, match=r"mask_head\.(point|coarse)_head.*which this model does not have"):
        init_detector(MaskRCNN(80, cfg), tmp_path / "pointrend.pkl")


def test_a_coarse_head_narrower_than_its_features_is_refused(monkeypatch):
    with pytest.raises(ValueError, match="conv_dim"):
        MaskRCNN(3, tiny_point_rend(monkeypatch, conv_dim=16))
