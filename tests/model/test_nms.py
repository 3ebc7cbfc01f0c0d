import pytest
import torch

from detection_oracles import nms_loop, torchvision_ops
from usl.model.ops import batched_nms, nms

TV = torchvision_ops()


def random_boxes(generator, count, spread=60.0, dtype=torch.float64):
    xy = torch.rand(count, 2, generator=generator, dtype=dtype) * spread
    return torch.cat([xy, xy + torch.rand(count, 2, generator=generator, dtype=dtype) * 30 + 0.5], dim=1)


@pytest.mark.parametrize("count", [0, 1, 7, 120, 700])
@pytest.mark.parametrize("threshold", [0.3, 0.7])
def test_nms_matches_greedy_reference_with_tied_scores(count, threshold):
    generator = torch.Generator().manual_seed(count)
    boxes = random_boxes(generator, count)
    scores = torch.randint(0, 6, (count,), generator=generator).double()  # many ties
    assert nms(boxes, scores, threshold).tolist() == nms_loop(boxes, scores, threshold)


@pytest.mark.parametrize("count", [0, 9, 300, 900])
def test_batched_nms_matches_per_group_reference(count):
    generator = torch.Generator().manual_seed(10 + count)
    boxes = random_boxes(generator, count, spread=30.0)
    scores = torch.randint(0, 20, (count,), generator=generator).double()
    groups = torch.randint(0, 4, (count,), generator=generator) * 3 - 2  # arbitrary (negative too) labels
    keep = batched_nms(boxes, scores, groups, 0.5)
    assert keep.tolist() == nms_loop(boxes, scores, 0.5, groups)


def test_identical_boxes_keep_first_of_tie_and_only_suppress_above_threshold():
    boxes = torch.tensor([[0.0, 0, 10, 10], [0.0, 0, 10, 10], [0.0, 0, 10, 5], [20.0, 20, 30, 30]])
    scores = torch.tensor([0.5, 0.5, 0.9, 0.1])
    # IoU(box 2, boxes 0/1) is exactly 0.5: kept at threshold 0.5 (strict >), dropped below.
    assert nms(boxes, scores, 0.5).tolist() == [2, 0, 3]
    assert nms(boxes, scores, 0.49).tolist() == [2, 3]


def test_float32_boxes_and_long_output():
    generator = torch.Generator().manual_seed(1)
    boxes = random_boxes(generator, 50, dtype=torch.float32)
    scores = torch.rand(50, generator=generator)
    keep = nms(boxes, scores, 0.5)
    assert keep.dtype == torch.long
    assert keep.tolist() == nms_loop(boxes.double(), scores.double(), 0.5)


@pytest.mark.skipif(TV is None, reason="torchvision ops do not run with this torch")
def test_equals_torchvision():
    generator = torch.Generator().manual_seed(2)
    boxes = random_boxes(generator, 500, dtype=torch.float32)
    scores = torch.rand(500, generator=generator)  # distinct scores: torchvision's tie order is unspecified
    groups = torch.randint(0, 5, (500,), generator=generator)
    assert torch.equal(nms(boxes, scores, 0.6), TV.nms(boxes, scores, 0.6))
    assert torch.equal(batched_nms(boxes, scores, groups, 0.6), TV.batched_nms(boxes, scores, groups, 0.6))
