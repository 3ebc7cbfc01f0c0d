"""Device-agnostic code paths on CUDA (skipped on CPU-only hosts)."""

import pytest
import torch

from tests.model.detection_scenes import make_dataset
from usl.model.detector import DetectorConfig, MaskRCNN
from usl.model.ops import batched_nms, roi_align

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")


def test_ops_agree_with_cpu():
    generator = torch.Generator().manual_seed(0)
    features = torch.randn(2, 8, 30, 40, generator=generator)
    xy = torch.rand(300, 2, generator=generator) * 150
    boxes = torch.cat([xy, xy + torch.rand(300, 2, generator=generator) * 60 + 1], dim=1)
    rois = torch.cat([torch.randint(0, 2, (300, 1), generator=generator).float(), boxes], dim=1)
    expected = roi_align(features, rois, 7, 0.25, 0, True)
    actual = roi_align(features.cuda(), rois.cuda(), 7, 0.25, 0, True).cpu()
    torch.testing.assert_close(actual, expected, atol=1e-5, rtol=1e-5)
    scores, groups = torch.rand(300, generator=generator), torch.randint(0, 3, (300,), generator=generator)
    kept = batched_nms(boxes.cuda(), scores.cuda(), groups.cuda(), 0.5)
    assert kept.is_cuda and kept.cpu().tolist() == batched_nms(boxes, scores, groups, 0.5).tolist()


def test_detector_trains_and_predicts_on_cuda():
    images, targets = make_dataset(2, seed=5)
    detector = MaskRCNN(2, DetectorConfig.tiny()).cuda().train()
    targets = [{k: v.cuda() for k, v in t.items()} for t in targets]
    losses = detector(images.cuda(), targets=targets)
    sum(losses.values()).backward()
    assert all(torch.isfinite(v) for v in losses.values())
    with torch.no_grad():
        outputs = detector.eval()(images.cuda())
    assert all(v.is_cuda for output in outputs for v in output.values())


def test_point_rend_masks_agree_with_cpu():
    from tests.model.test_point_rend import tiny_point_rend

    torch.manual_seed(0)
    detector = MaskRCNN(3, tiny_point_rend()).eval()
    torch.nn.init.normal_(detector.roi_heads.mask_head.point_head.predictor.weight, std=1.0)
    features = {"p2": torch.randn(2, 32, 16, 16)}
    boxes = [torch.tensor([[4.0, 6.0, 40.0, 50.0]]), torch.tensor([[10.0, 10.0, 60.0, 30.0], [0.0, 0.0, 64, 64]])]
    classes = torch.tensor([0, 2, 1])
    head = detector.roi_heads.mask_head
    with torch.no_grad():
        expected = head.predict(features, boxes, classes)
        actual = head.cuda().predict({"p2": features["p2"].cuda()}, [b.cuda() for b in boxes], classes.cuda())
    # the 784 most uncertain cells may differ where logits tie; nearly all cells must agree
    close = torch.isclose(actual.cpu(), expected, atol=1e-3, rtol=1e-3)
    assert actual.is_cuda and close.float().mean() > 0.999
