import pytest
import torch

from tests.model.detection_oracles import nms_loop, torchvision_ops
from usl.model.ops import batched_nms, nms
import importlib

NMS = importlib.import_module("usl.model.ops.nms")

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


@pytest.mark.parametrize("count", [0, 1, 2, 150, 400])
@pytest.mark.parametrize("threshold", [-0.1, 0.0, 0.3, 0.5, 0.7, 1.0])
def test_pure_torch_graph_path_equals_the_compiled_loop_and_the_reference(count, threshold):
    generator = torch.Generator().manual_seed(20 + count)
    boxes = random_boxes(generator, count, spread=40.0, dtype=torch.float32)
    if count > 2:  # degenerate, inverted, NaN and infinite boxes never suppress (IoU 0 or NaN)
        boxes[0] = torch.tensor([5.0, 5.0, 5.0, 9.0])
        boxes[1] = torch.tensor([9.0, 9.0, 3.0, 3.0])
        boxes[2, 0] = float("nan")
        boxes[3, 2] = float("inf")
    scores = torch.randint(0, 8, (count,), generator=generator).float()
    groups = torch.randint(0, 3, (count,), generator=generator)
    expected = nms_loop(boxes, scores, threshold) if count <= 150 else nms(boxes, scores, threshold).tolist()
    assert NMS._pure_torch_nms(boxes, scores, threshold).tolist() == expected
    assert nms(boxes, scores, threshold).tolist() == expected
    pure = NMS._pure_torch_batched_nms(boxes, scores, groups, threshold)
    assert pure.tolist() == batched_nms(boxes, scores, groups, threshold).tolist()
    if count <= 150:
        assert pure.tolist() == nms_loop(boxes, scores, threshold, groups)


def test_threshold_is_compared_as_a_real_number():
    # float32(0.3) lies above 0.3: an IoU of exactly that value exceeds the threshold (torchvision's test)
    iou = torch.tensor([0.3, 0.5, 0.7], dtype=torch.float32)
    assert NMS._above(iou, 0.3).tolist() == [True, True, True]
    assert NMS._above(iou, 0.5).tolist() == [False, False, True]
    assert NMS._above(iou, 0.7).tolist() == [False, False, False]  # float32(0.7) lies below 0.7
    assert NMS._above(iou.double(), 0.3).tolist() == [True, True, True]


@pytest.mark.skipif(TV is None, reason="torchvision ops do not run with this torch")
def test_equals_torchvision():
    generator = torch.Generator().manual_seed(2)
    boxes = random_boxes(generator, 500, dtype=torch.float32)
    scores = torch.rand(500, generator=generator)  # distinct scores: torchvision's tie order is unspecified
    groups = torch.randint(0, 5, (500,), generator=generator)
    assert torch.equal(nms(boxes, scores, 0.6), TV.nms(boxes, scores, 0.6))
    assert torch.equal(batched_nms(boxes, scores, groups, 0.6), TV.batched_nms(boxes, scores, groups, 0.6))
    # What nms() dispatches to on CUDA: torchvision with our tie order, proven equal on the probe set.
    tied = torch.randint(0, 10, (500,), generator=generator).float()
    for threshold in (0.3, 0.5, 0.7):
        assert torch.equal(NMS._torchvision_nms(boxes, tied, threshold), NMS._pure_torch_nms(boxes, tied, threshold))
        assert torch.equal(
            NMS._torchvision_batched_nms(boxes, tied, groups, threshold),
            NMS._pure_torch_batched_nms(boxes, tied, groups, threshold),
        )
    assert NMS._agrees_with_torchvision(torch.device("cpu"))
