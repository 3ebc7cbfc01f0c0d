"""Evaluation metrics: Chamfer / F1 (scipy cKDTree oracle), mask IoU (pycocotools oracle),
box gIoU and boxes of masks (hand cases), nearest-depth L1."""

import numpy as np
import pycocotools.mask as mask_utils
import pytest
import torch
from scipy.spatial import cKDTree

from usl.geometry.icosphere import ico_sphere
from usl.geometry.meshes import Meshes
from usl.metrics import box_giou, chamfer_f1, compare_meshes, depth_l1, mask_iou, masks_to_boxes, nearest_depth


def test_chamfer_f1_matches_cKDTree_with_padding_and_several_thresholds():
    gen = torch.Generator().manual_seed(0)
    pred = torch.rand(3, 700, 3, generator=gen, dtype=torch.float64)
    gt = torch.rand(3, 500, 3, generator=gen, dtype=torch.float64) * 1.2
    pred_len, gt_len = torch.tensor([700, 300, 50]), torch.tensor([500, 500, 20])
    out = chamfer_f1(pred, gt, pred_len, gt_len, thresholds=(0.05, 0.1), max_elements=20_000, backend="torch")
    fast = chamfer_f1(pred, gt, pred_len, gt_len, thresholds=(0.05, 0.1), backend="kdtree")
    for key in out:
        torch.testing.assert_close(fast[key], out[key], rtol=1e-4, atol=1e-5)
    for b in range(3):
        p, g = pred[b, : pred_len[b]].numpy(), gt[b, : gt_len[b]].numpy()
        d_pg, _ = cKDTree(g).query(p)
        d_gp, _ = cKDTree(p).query(g)
        assert out["Chamfer-L2"][b].item() == pytest.approx(np.mean(d_pg**2) + np.mean(d_gp**2), rel=1e-9)
        for t in (0.05, 0.1):
            precision, recall = 100 * np.mean(d_pg < t), 100 * np.mean(d_gp < t)
            f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
            assert out[f"Precision@{t:g}"][b].item() == pytest.approx(precision)
            assert out[f"Recall@{t:g}"][b].item() == pytest.approx(recall)
            assert out[f"F1@{t:g}"][b].item() == pytest.approx(f1)


def test_compare_meshes_on_identical_and_disjoint_spheres():
    v, f = ico_sphere(3)
    gt = Meshes.from_shared_topology(torch.stack([v * 0.3, v * 0.3]), f)
    pred = Meshes.from_shared_topology(torch.stack([v * 0.3, v * 0.3 + torch.tensor([1.0, 0.0, 0.0])]), f)
    out = compare_meshes(pred, gt, num_samples=4000, generator=torch.Generator().manual_seed(1))
    assert out["F1@0.1"].tolist() == pytest.approx([100.0, 0.0])
    assert out["Chamfer-L2"][0] < 1e-3
    # disjoint: every nearest distance is at least the 0.4 m gap between the spheres
    assert out["Chamfer-L2"][1] > 2 * 0.4**2


def test_mask_iou_matches_pycocotools():
    gen = torch.Generator().manual_seed(2)
    pred = torch.rand(5, 17, 23, generator=gen) > 0.5
    true = torch.rand(5, 17, 23, generator=gen) > 0.3
    ious = mask_iou(pred, true)
    for p, t, iou in zip(pred, true, ious, strict=True):
        rp = mask_utils.encode(np.asfortranarray(p.numpy().astype(np.uint8)))
        rt = mask_utils.encode(np.asfortranarray(t.numpy().astype(np.uint8)))
        assert iou.item() == pytest.approx(mask_utils.iou([rp], [rt], [0])[0, 0], rel=1e-6)


def test_mask_iou_hand_cases():
    a = torch.zeros(2, 3, 4, 4, dtype=torch.bool)
    b = torch.zeros_like(a)
    a[0, 0, :2, :2] = True
    b[0, 0, :2, :] = True  # 4 of 8: 0.5
    a[0, 1] = b[0, 1] = True  # identical: 1
    a[1, 0, 0, 0] = True  # disjoint from an empty mask: 0
    ious = mask_iou(a, b.float())
    assert ious[0].tolist() == [0.5, 1.0, 0.0] and ious[1].tolist() == [0.0, 0.0, 0.0]
    assert torch.isnan(mask_iou(a[1, 1], b[1, 1], empty_value=float("nan")))


def test_box_giou_hand_cases():
    a = torch.tensor([[0.0, 0, 1, 1], [0, 0, 1, 1], [0, 0, 2, 2], [0, 0, 4, 4]])
    b = torch.tensor([[0.0, 0, 1, 1], [2, 0, 3, 1], [1, 1, 3, 3], [1, 1, 2, 2]])
    expected = [1.0, -1 / 3, 1 / 7 - 2 / 9, 1 / 16]
    np.testing.assert_allclose(box_giou(a, b).numpy(), expected, rtol=1e-6)
    np.testing.assert_allclose(box_giou(b, a).numpy(), expected, rtol=1e-6)
    far = box_giou(torch.tensor([0.0, 0, 1, 1]), torch.tensor([100.0, 100, 101, 101]))
    assert -1 < far.item() < -0.99
    assert box_giou(a[None].expand(2, -1, -1), b).shape == (2, 4)


def test_masks_to_boxes_uses_pixel_edges():
    masks = torch.zeros(3, 5, 6, dtype=torch.bool)
    masks[0, 2, 3] = True
    masks[1, 1:4, 0:2] = True
    boxes = masks_to_boxes(masks)
    assert boxes[0].tolist() == [3.0, 2.0, 4.0, 3.0]
    assert boxes[1].tolist() == [0.0, 1.0, 2.0, 4.0]
    assert torch.isnan(boxes[2]).all()


def test_nearest_depth_and_l1():
    depth = torch.tensor([[[2.0, 0.0, 3.0], [float("nan"), 1.5, 4.0]]]).expand(2, -1, -1)
    mask = torch.tensor([[[True, True, False], [True, False, True]], [[False, True, False], [True, False, False]]])
    near = nearest_depth(depth, mask)
    assert near[0].item() == 2.0 and torch.isnan(near[1])  # unknown (0 / NaN) pixels are skipped
    err = depth_l1(near, torch.tensor([2.5, 1.0]))
    assert err[0].item() == 0.5 and torch.isnan(err[1]) and torch.nanmean(err).item() == 0.5
