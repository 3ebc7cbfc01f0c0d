import math

import pytest
import torch

from tests.model.detection_oracles import iou_single
from usl.model.ops import AnchorGenerator, Box2BoxTransform, box_area, box_iou, clip_boxes, nonempty_boxes
from usl.utils.op_count import count_ops


def random_boxes(generator, count):
    xy = torch.rand(count, 2, generator=generator, dtype=torch.float64) * 50
    return torch.cat([xy, xy + torch.rand(count, 2, generator=generator, dtype=torch.float64) * 40 + 0.1], dim=1)


def test_box_iou_matches_pairwise_loop():
    generator = torch.Generator().manual_seed(0)
    a, b = random_boxes(generator, 7), random_boxes(generator, 5)
    expected = torch.tensor([[iou_single(x, y) for y in b.tolist()] for x in a.tolist()], dtype=torch.float64)
    torch.testing.assert_close(box_iou(a, b), expected)
    torch.testing.assert_close(box_area(a), (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1]))


def test_clip_and_nonempty():
    boxes = torch.tensor([[-5.0, -2.0, 30.0, 8.0], [12.0, 3.0, 14.0, 3.0]])
    expected = torch.tensor([[0.0, 0.0, 20.0, 8.0], [12.0, 3.0, 14.0, 3.0]])
    torch.testing.assert_close(clip_boxes(boxes, (10, 20)), expected)
    assert nonempty_boxes(boxes).tolist() == [True, False]


@pytest.mark.parametrize("weights", [(1.0, 1.0, 1.0, 1.0), (10.0, 10.0, 5.0, 5.0)])
def test_encode_decode_round_trip(weights):
    generator = torch.Generator().manual_seed(1)
    src, dst = random_boxes(generator, 20), random_boxes(generator, 20)
    transform = Box2BoxTransform(weights)
    deltas = transform.get_deltas(src, dst)
    torch.testing.assert_close(transform.apply_deltas(deltas, src).double(), dst, rtol=1e-5, atol=1e-4)


def test_known_deltas_and_class_specific_decoding():
    transform = Box2BoxTransform((10.0, 10.0, 5.0, 5.0))
    src = torch.tensor([[0.0, 0.0, 10.0, 20.0]])
    dst = torch.tensor([[5.0, 0.0, 25.0, 20.0]])  # centre +10 in x (one width), width doubled
    torch.testing.assert_close(transform.get_deltas(src, dst), torch.tensor([[10.0, 0.0, 5 * math.log(2.0), 0.0]]))
    per_class = torch.cat([torch.zeros(1, 4), transform.get_deltas(src, dst)], dim=1)  # (1, 2 classes * 4)
    torch.testing.assert_close(transform.apply_deltas(per_class, src), torch.cat([src, dst], dim=1))


def test_scale_clamp_bounds_growth():
    transform = Box2BoxTransform((1.0, 1.0, 1.0, 1.0), scale_clamp=math.log(4.0))
    decoded = transform.apply_deltas(torch.tensor([[0.0, 0.0, 50.0, 50.0]]), torch.tensor([[0.0, 0.0, 2.0, 2.0]]))
    torch.testing.assert_close(decoded, torch.tensor([[-3.0, -3.0, 5.0, 5.0]]))


def test_anchor_counts_positions_and_shapes_per_level():
    generator = AnchorGenerator(sizes=((8,), (16, 24)), aspect_ratios=(0.5, 1.0, 2.0), strides=(4, 8), offset=0.5)
    assert generator.num_anchors_per_location == [3, 6]
    level0, level1 = generator([(5, 7), (3, 4)])
    assert level0.shape == (5 * 7 * 3, 4) and level1.shape == (3 * 4 * 6, 4)
    for anchors, stride, width, per_location, sizes in ((level0, 4, 7, 3, (8,)), (level1, 8, 4, 6, (16, 24))):
        centres = (anchors[:, :2] + anchors[:, 2:]) / 2
        wh = anchors[:, 2:] - anchors[:, :2]
        # Location-major layout: row (y * W + x) * A + a is centred at ((x + 0.5) s, (y + 0.5) s).
        index = torch.arange(len(anchors)) // per_location
        expected = torch.stack([(index % width + 0.5) * stride, (index // width + 0.5) * stride], dim=1).float()
        torch.testing.assert_close(centres, expected)
        areas = torch.tensor([s * s for s in sizes for _ in range(3)] * (len(anchors) // per_location)).float()
        ratios = torch.tensor([0.5, 1.0, 2.0] * (len(anchors) // 3))
        torch.testing.assert_close(wh[:, 0] * wh[:, 1], areas)
        torch.testing.assert_close(wh[:, 1] / wh[:, 0], ratios)


def test_anchor_grids_are_built_once_per_feature_size():
    generator = AnchorGenerator(sizes=((8,), (16,)), aspect_ratios=(1.0,), strides=(4, 8))
    first = generator([(5, 7), (3, 4)])
    with count_ops() as count:
        again = generator([(5, 7), (3, 4)])
    assert count.ops == 0 and all(torch.equal(a, b) for a, b in zip(first, again, strict=True))
    other = generator([(6, 7), (3, 4)])
    assert other[0].shape == (6 * 7, 4) and torch.equal(other[0][: 5 * 7], first[0])
    for height in range(20):  # a bounded cache: many sizes (evaluation) do not grow it without end
        generator([(height + 1, 2), (1, 1)])
    assert len(generator._grids) <= 8


def test_anchor_generator_rejects_mismatched_levels():
    with pytest.raises(ValueError, match="one size list per level"):
        AnchorGenerator(sizes=((8,),), aspect_ratios=(1.0,), strides=(4, 8))
