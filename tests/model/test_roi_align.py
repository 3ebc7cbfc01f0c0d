import importlib
import itertools

import numpy as np
import pytest
import torch

from tests.model.detection_oracles import roi_align_loop, torchvision_ops
from usl.model.detector import MultiScaleRoIAlign, assign_boxes_to_levels
from usl.model.ops import RoIAlign, autocast_off, convert_boxes_to_rois, roi_align

TV = torchvision_ops()


def random_rois(generator, count, num_images, extent, dtype=torch.float64):
    """Boxes of all sizes, many partly (some wholly) outside a map of ``extent`` pixels."""
    xy = torch.rand(count, 2, generator=generator, dtype=dtype) * (extent * 1.4) - extent * 0.3
    wh = torch.rand(count, 2, generator=generator, dtype=dtype) * extent * 0.8 + 0.1
    batch = torch.randint(0, num_images, (count, 1), generator=generator).to(dtype)
    rois = torch.cat([batch, xy, xy + wh], dim=1)
    rois[0, 3:] = rois[0, 1:3]  # a degenerate (zero-size) box
    rois[1, 1:] = torch.tensor([-9.0, -9.0, -4.0, -3.0], dtype=dtype)  # wholly outside
    return rois


@pytest.mark.parametrize(
    "aligned,sampling_ratio,spatial_scale", list(itertools.product([True, False], [-1, 1, 2], [1.0, 0.5, 0.3]))
)
def test_matches_loop_reference(aligned, sampling_ratio, spatial_scale):
    generator = torch.Generator().manual_seed(hash((aligned, sampling_ratio, spatial_scale)) % 1000)
    features = torch.randn(2, 3, 9, 11, generator=generator, dtype=torch.float64)
    rois = random_rois(generator, 10, 2, 11 / spatial_scale)
    expected = roi_align_loop(features, rois, (3, 4), spatial_scale, sampling_ratio, aligned)
    actual = roi_align(features, rois, (3, 4), spatial_scale, sampling_ratio, aligned)
    torch.testing.assert_close(actual, expected, rtol=0, atol=1e-12)


def test_adaptive_grid_with_large_and_small_boxes_and_tiny_chunks():
    """Heterogeneous adaptive grids (1..~8 samples per bin) and a budget forcing one RoI per chunk."""
    generator = torch.Generator().manual_seed(3)
    features = torch.randn(1, 2, 40, 30, generator=generator, dtype=torch.float64)
    rois = torch.tensor(
        [[0, 1.0, 2.0, 3.0, 3.5], [0, -5.0, -2.0, 33.0, 41.0], [0, 4.0, 4.0, 20.0, 9.0]], dtype=torch.float64
    )
    expected = roi_align_loop(features, rois, (5, 5), 1.0, 0, True)
    for budget in (1, 10**9):
        actual = roi_align(features, rois, 5, 1.0, 0, True, max_chunk_elements=budget)
        torch.testing.assert_close(actual, expected, rtol=0, atol=1e-12)


def test_gradients_of_many_chunks_match_the_loop_reference(monkeypatch):
    """Chunks are strided views of plan-ordered matrices and of the output: with one RoI per chunk,
    a few chunks, or one, the input gradient is the per-sample loop's (through autograd)."""
    generator = torch.Generator().manual_seed(7)
    features = torch.randn(2, 3, 20, 24, generator=generator, dtype=torch.float64)
    rois = random_rois(generator, 14, 2, 24)
    weight = torch.randn(14, 3, 3, 4, generator=generator, dtype=torch.float64)
    leaf = features.clone().requires_grad_(True)
    (roi_align_loop(leaf, rois, (3, 4), 1.0, -1, True) * weight).sum().backward()
    module = importlib.import_module("usl.model.ops.roi_align")  # the module, not the function of that name
    chunks, plan_chunks = [], module._plan_chunks
    monkeypatch.setattr(module, "_plan_chunks", lambda *args: chunks.append(len(plan := plan_chunks(*args))) or plan)
    for budget in (1, 3000, 10**9):  # 14, 4 and 1 chunks
        mine = features.clone().requires_grad_(True)
        (roi_align(mine, rois, (3, 4), 1.0, -1, True, max_chunk_elements=budget) * weight).sum().backward()
        torch.testing.assert_close(mine.grad, leaf.grad, rtol=0, atol=1e-12)
    assert chunks == [14, 4, 1]


def test_list_of_boxes_equals_rois_tensor_and_module():
    generator = torch.Generator().manual_seed(4)
    features = torch.randn(2, 4, 8, 8, generator=generator)
    boxes = [torch.tensor([[1.0, 1.0, 6.0, 5.0]]), torch.tensor([[0.0, 2.0, 7.5, 7.0], [2.0, 2.0, 3.0, 3.0]])]
    rois = convert_boxes_to_rois(boxes, features)
    assert rois[:, 0].tolist() == [0, 1, 1]
    module = RoIAlign((2, 2), spatial_scale=1.0, sampling_ratio=2, aligned=True)
    torch.testing.assert_close(module(features, boxes), roi_align(features, rois, 2, 1.0, 2, True))


def test_empty_rois_and_bad_batch_index():
    features = torch.randn(1, 3, 5, 5)
    assert roi_align(features, torch.zeros(0, 5), 2).shape == (0, 3, 2, 2)
    with pytest.raises(ValueError, match="batch indices"):
        roi_align(features, torch.tensor([[1.0, 0, 0, 2, 2]]), 2)


def test_bool_input_pooled_as_float():
    mask = torch.zeros(1, 1, 6, 6, dtype=torch.bool)
    mask[..., :, :3] = True
    pooled = roi_align(mask, torch.tensor([[0.0, 0.0, 0.0, 6.0, 6.0]]), 2, 1.0, 2, True)
    assert pooled.dtype == torch.float32
    torch.testing.assert_close(pooled[0, 0], torch.tensor([[1.0, 0.0], [1.0, 0.0]]))


@pytest.mark.parametrize("aligned,sampling_ratio", [(True, -1), (False, 2)])
def test_gradcheck_float64(aligned, sampling_ratio):
    generator = torch.Generator().manual_seed(5)
    features = torch.randn(2, 2, 5, 6, generator=generator, dtype=torch.float64, requires_grad=True)
    rois = torch.tensor(
        [[0, 0.3, 0.7, 4.2, 3.9], [1, -1.2, 1.1, 3.3, 6.0], [1, 2.2, 0.4, 7.1, 2.5]], dtype=torch.float64
    )
    assert torch.autograd.gradcheck(
        lambda x: roi_align(x, rois, (2, 3), 0.8, sampling_ratio, aligned), (features,), eps=1e-6, atol=1e-8
    )


@pytest.mark.skipif(TV is None, reason="torchvision ops do not run with this torch")
@pytest.mark.parametrize("aligned,sampling_ratio", [(True, 0), (False, 2)])
def test_equals_torchvision(aligned, sampling_ratio):
    generator = torch.Generator().manual_seed(6)
    features = torch.randn(2, 3, 12, 10, generator=generator)
    rois = random_rois(generator, 20, 2, 20, dtype=torch.float32)
    expected = TV.roi_align(features, rois, (4, 4), 0.5, sampling_ratio, aligned)
    torch.testing.assert_close(roi_align(features, rois, (4, 4), 0.5, sampling_ratio, aligned), expected)


def test_autocast_pools_in_float32():
    """Under bf16 autocast (as training on CUDA runs), the pooling stays in float32, as torchvision's
    autocast rule keeps it: the result is the float32 pooling of the bf16 features, rounded once."""
    generator = torch.Generator().manual_seed(8)
    features = torch.randn(2, 3, 12, 10, generator=generator).to(torch.bfloat16).requires_grad_()
    rois = random_rois(generator, 12, 2, 12, dtype=torch.float32)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        pooled = roi_align(features, rois, (3, 4), 1.0, 2, True)
        pooled.float().square().sum().backward()
    reference = features.detach().float().requires_grad_()
    expected = roi_align(reference, rois, (3, 4), 1.0, 2, True)
    expected.to(torch.bfloat16).float().square().sum().backward()
    assert pooled.dtype == torch.bfloat16
    torch.testing.assert_close(pooled, expected.to(torch.bfloat16), rtol=0, atol=0)
    torch.testing.assert_close(features.grad.float(), reference.grad, rtol=1e-2, atol=1e-2)


def test_autocast_off_disables_it_and_passes_devices_without_it():
    with torch.autocast("cpu", dtype=torch.bfloat16):
        with autocast_off("cpu"):
            assert not torch.is_autocast_enabled("cpu")
            assert (torch.ones(2, 2) @ torch.ones(2, 2)).dtype == torch.float32
        assert torch.is_autocast_enabled("cpu")
    with autocast_off("meta"):  # torch.autocast("meta", enabled=False) raises
        assert torch.empty(2, device="meta").is_meta


def test_fpn_levels_in_one_pass_match_one_call_per_level():
    """MultiScaleRoIAlign pools all levels at once; the former loop (one roi_align per level, its
    RoIs found with nonzero) is the oracle, for values and for each level's gradient."""
    generator = torch.Generator().manual_seed(5)
    pooler = MultiScaleRoIAlign(["p2", "p3", "p4"], [4, 8, 16], 5, sampling_ratio=0, canonical_box_size=32)
    shapes = {"p2": (24, 32), "p3": (12, 16), "p4": (6, 8)}
    maps = {k: torch.randn(2, 3, h, w, generator=generator, dtype=torch.float64) for k, (h, w) in shapes.items()}
    boxes = [random_rois(generator, 12, 1, 128)[:, 1:].abs() for _ in range(2)]
    rois = convert_boxes_to_rois(boxes, maps["p2"])
    level = assign_boxes_to_levels(rois[:, 1:], 2, 4, 32, 4)
    assert len(level.unique()) == 3  # every level has RoIs
    results = []
    for one_pass in (True, False):
        leaves = {k: v.clone().requires_grad_(True) for k, v in maps.items()}
        if one_pass:
            pooled = pooler(leaves, boxes)
        else:
            pooled = torch.zeros(len(rois), 3, 5, 5, dtype=torch.float64)
            for index, (name, stride) in enumerate(zip(["p2", "p3", "p4"], [4, 8, 16], strict=True)):
                rows = torch.nonzero(level == index).squeeze(1)
                pooled[rows] = roi_align(leaves[name], rois[rows], 5, 1.0 / stride, 0, aligned=True)
        (pooled * torch.linspace(-1, 1, pooled.numel(), dtype=torch.float64).view_as(pooled)).sum().backward()
        results.append((pooled.detach(), [leaves[k].grad for k in shapes]))
    torch.testing.assert_close(results[0][0], results[1][0], rtol=0, atol=1e-12)
    for new, old in zip(results[0][1], results[1][1], strict=True):
        torch.testing.assert_close(new, old, rtol=0, atol=1e-12)


def test_chunk_plan_covers_every_roi_once_within_memory_and_merges_where_padding_is_cheap():
    from usl.model.ops.roi_align import _CHUNK_COST, _plan_chunks

    rng = np.random.default_rng(0)
    heights = np.ceil(rng.uniform(1, 50, 1000) ** rng.uniform(0.5, 1.0, 1000))
    widths = np.ceil(rng.uniform(1, 50, 1000) ** rng.uniform(0.5, 1.0, 1000))
    for channels, budget in ((256, 1 << 24), (1, 1 << 24), (256, 1 << 16)):
        plan = _plan_chunks(heights, widths, channels, budget)
        rois = np.concatenate([index for index, _, _ in plan])
        assert sorted(rois.tolist()) == list(range(len(heights)))
        for index, h, w in plan:
            assert h == heights[index].max() and w == widths[index].max()
            assert len(index) == 1 or len(index) * channels * h * w <= budget
        cost = sum(len(index) * channels * h * w + _CHUNK_COST for index, h, w in plan)
        one_per_size = {(h, w): 0 for h, w in zip(heights, widths, strict=True)}
        for h, w in zip(heights, widths, strict=True):
            one_per_size[(h, w)] += 1
        unmerged = sum(  # no padding at all: one chunk per window size (split to fit the budget)
            n * channels * h * w + -(-n // max(1, budget // (channels * h * w))) * _CHUNK_COST
            for (h, w), n in one_per_size.items()
        )
        assert cost <= unmerged
