import importlib

import pytest
import torch

from tests.model.detection_oracles import nms_loop, torchvision_ops
from usl.model.ops import batched_nms, nms

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


def compiled_nms(boxes, scores, threshold, groups=None):
    return NMS._compiled_batched_nms(boxes, scores, groups, threshold).tolist()


def pure_nms(boxes, scores, threshold, groups=None):
    if groups is None:
        return NMS._pure_torch_nms(boxes, scores, threshold).tolist()
    return NMS._pure_torch_batched_nms(boxes, scores, groups, threshold).tolist()


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_long_suppression_chain_needs_many_rounds(dtype):
    # Box k overlaps box k + 1 (IoU 0.82) but not box k + 2 (IoU 0.67) at threshold 0.7, scores
    # falling along the chain: whether box k is kept depends on all before it (k rounds).
    count = 150
    x = torch.arange(count, dtype=dtype) * 1.0
    boxes = torch.stack([x, torch.zeros_like(x), x + 10, torch.full_like(x, 10)], 1)
    scores = torch.linspace(1, 0, count, dtype=dtype)
    expected = list(range(0, count, 2))
    assert nms_loop(boxes, scores, 0.7) == expected
    assert pure_nms(boxes, scores, 0.7) == compiled_nms(boxes, scores, 0.7) == expected


def test_groups_that_share_a_hash_field_do_not_suppress_each_other():
    boxes = torch.tensor([[0.0, 0, 10, 10], [0.0, 0, 10, 10.5], [0.0, 0, 10, 11], [1.0, 0, 11, 10]]).double()
    scores = torch.tensor([0.9, 0.8, 0.7, 0.6]).double()
    groups = torch.tensor([5, 5 + 1024, -(1 << 40) + 5, 5])  # equal modulo 2^10
    assert pure_nms(boxes, scores, 0.5, groups) == nms_loop(boxes, scores, 0.5, groups) == [0, 1, 2]
    assert pure_nms(boxes, scores, 0.5, torch.tensor([7, 7 + 1024, 7 + 2048, 7], dtype=torch.int32)) == [0, 1, 2]


@pytest.mark.parametrize("offset", [0.0, 1e7, -3e9])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_far_and_tiny_boxes_whose_cells_clamp_together(offset, dtype):
    # far from the origin (cells beyond +-2^19 clamp into one) and tiny boxes (fine grids)
    generator = torch.Generator().manual_seed(3)
    boxes = random_boxes(generator, 300, spread=40.0, dtype=torch.float64)
    boxes[::3] = boxes[::3] * 1e-6
    boxes[1::3, 0::2] += offset
    boxes = boxes.to(dtype)
    scores = torch.randint(0, 5, (300,), generator=generator).to(dtype)
    groups = torch.randint(0, 3, (300,), generator=generator)
    assert pure_nms(boxes, scores, 0.5) == compiled_nms(boxes, scores, 0.5)
    assert pure_nms(boxes, scores, 0.5, groups) == compiled_nms(boxes, scores, 0.5, groups)


@pytest.mark.parametrize("threshold", [0.0, 0.01, 0.999, 1.0 - 1e-9, 1.0])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_extreme_thresholds_equal_the_compiled_loop_and_the_python_loop(threshold, dtype):
    generator = torch.Generator().manual_seed(4)
    boxes = random_boxes(generator, 120, spread=20.0, dtype=torch.float64)
    boxes[60:] = boxes[:60]  # duplicates: IoU exactly 1
    boxes[100:110] = boxes[100:110].round()  # boxes touching at an edge: IoU 0 and ties
    scores = torch.randint(0, 4, (120,), generator=generator).double()
    groups = torch.randint(0, 2, (120,), generator=generator)
    expected = nms_loop(boxes, scores, threshold, groups)
    boxes, scores = boxes.to(dtype), scores.to(dtype)
    assert pure_nms(boxes, scores, threshold, groups) == compiled_nms(boxes, scores, threshold, groups)
    if dtype == torch.float64:
        assert pure_nms(boxes, scores, threshold, groups) == expected


@pytest.mark.parametrize("count", [2, 40])
def test_unusable_boxes_never_suppress_and_are_kept(count):
    boxes = torch.full((count, 4), float("nan"))
    boxes[::2] = torch.tensor([0.0, 0.0, 0.0, 5.0])  # empty
    boxes[1::4] = torch.tensor([0.0, 0.0, float("inf"), 5.0])
    scores = torch.arange(count, dtype=torch.float32)
    assert pure_nms(boxes, scores, 0.5) == compiled_nms(boxes, scores, 0.5) == list(range(count - 1, -1, -1))


def test_float16_threshold_is_compared_as_a_real_number():
    iou = torch.tensor([0.3, 0.5, 0.7], dtype=torch.float16)  # each rounded off its decimal threshold
    expected = [float(v) > t for v, t in zip(iou.double().tolist(), (0.3, 0.5, 0.7), strict=True)]
    assert [bool(NMS._above(iou[k : k + 1], t)) for k, t in enumerate((0.3, 0.5, 0.7))] == expected
    assert NMS._above(iou.bfloat16(), 0.5).tolist() == [float(v) > 0.5 for v in iou.bfloat16().double().tolist()]


@pytest.mark.parametrize("count, groups", [(60, 1), (3000, 1), (3000, 37)])
def test_pure_torch_path_reads_the_device_twice_whatever_the_boxes_and_groups(count, groups):
    """The count of candidate pairs, then both fixed-point counts after a batch of rounds."""
    from usl.utils.op_count import count_ops

    generator = torch.Generator().manual_seed(5)
    boxes = random_boxes(generator, count, spread=8 * count**0.5, dtype=torch.float32)
    scores = torch.rand(count, generator=generator)
    labels = torch.randint(0, groups, (count,), generator=generator)
    with count_ops() as counted:
        kept = NMS._pure_torch_batched_nms(boxes, scores, labels, 0.7)
    assert counted.total_syncs == 2 and counted.uploads == 0, counted.syncs
    assert kept.tolist() == compiled_nms(boxes, scores, 0.7, labels)


def test_kept_by_image_orders_each_image_as_if_alone():
    image = torch.tensor([1, 0, 1, 2, 0, 1])
    kept = torch.tensor([5, 1, 0, 4, 2])  # in decreasing score order over all images
    assert [k.tolist() for k in NMS.kept_by_image(kept, image, 4)] == [[1, 4], [5, 0, 2], [], []]


def test_candidates_beyond_a_chunk_are_tested_in_chunks_and_iterated_as_edges(monkeypatch):
    generator = torch.Generator().manual_seed(6)
    boxes = random_boxes(generator, 400, spread=30.0, dtype=torch.float32)
    scores = torch.randint(0, 6, (400,), generator=generator).float()
    groups = torch.randint(0, 3, (400,), generator=generator)
    expected = pure_nms(boxes, scores, 0.5, groups)
    monkeypatch.setattr(NMS, "_CHUNK_ELEMENTS", 257)  # many chunks
    assert pure_nms(boxes, scores, 0.5, groups) == expected == compiled_nms(boxes, scores, 0.5, groups)
