"""The 2D silhouette losses: mask point sampling, l_dist, l_xent and its IoU gate, l_2D."""

import math

import numpy as np
import pytest
import torch

from usl.geometry.cameras import scale_intrinsics
from usl.losses.silhouette import (
    l2d_loss,
    sample_mask_points,
    silhouette_bce_loss,
    silhouette_chamfer_loss,
    soft_iou_loss,
)

DT = torch.float64
K = torch.tensor([[60.0, 0.0, 40.0], [0.0, 55.0, 30.0], [0.0, 0.0, 1.0]], dtype=DT)


def test_sample_mask_points_takes_all_pixels_of_small_masks_at_their_centres():
    masks = torch.zeros(3, 6, 7, dtype=torch.bool)
    pixels = [(1, 2), (1, 3), (4, 6), (5, 0), (2, 2)]  # (row, col)
    for r, c in pixels:
        masks[0, r, c] = True
    masks[1] = True
    points, lengths = sample_mask_points(masks, 8, jitter=False, generator=torch.Generator().manual_seed(0))
    assert points.shape == (3, 8, 2) and lengths.tolist() == [5, 8, 0]
    got = {(float(u), float(v)) for u, v in points[0, :5].tolist()}
    assert got == {(c + 0.5, r + 0.5) for r, c in pixels}
    assert (points[0, 5:] == 0).all() and (points[2] == 0).all()
    assert len({tuple(p) for p in points[1].tolist()}) == 8  # distinct pixels


def test_sample_mask_points_jitter_stays_inside_mask_pixels_and_crops_map_to_their_box():
    gen = torch.Generator().manual_seed(1)
    masks = torch.rand(4, 20, 30, generator=gen) > 0.6
    points, lengths = sample_mask_points(masks.float(), 50, generator=gen)
    for m, pts, n in zip(masks, points, lengths, strict=True):
        cols, rows = pts[:n, 0].floor().long(), pts[:n, 1].floor().long()
        assert m[rows, cols].all()
    crop = torch.ones(1, 4, 4, dtype=torch.bool)
    box = torch.tensor([[10.0, 20.0, 18.0, 40.0]])
    points, _ = sample_mask_points(crop, 16, boxes=box, jitter=False)
    us, vs = sorted({p[0] for p in points[0].tolist()}), sorted({p[1] for p in points[0].tolist()})
    assert us == [11.0, 13.0, 15.0, 17.0] and vs == [22.5, 27.5, 32.5, 37.5]


def test_sample_mask_points_is_uniform_over_the_silhouette():
    mask = torch.zeros(10, 10, dtype=torch.bool)
    mask[2:6, 1:9] = True  # 32 pixels, sample 8 of them per draw
    draws = 4000
    points, _ = sample_mask_points(
        mask.expand(draws, -1, -1), 8, jitter=False, generator=torch.Generator().manual_seed(2)
    )
    counts = np.zeros((10, 10))
    np.add.at(counts, (points[..., 1].floor().long().numpy(), points[..., 0].floor().long().numpy()), 1)
    freq = counts[2:6, 1:9] / draws
    assert counts.sum() == draws * 8 and abs(freq - 0.25).max() < 5 * math.sqrt(0.25 * 0.75 / draws)


def _oracle_chamfer(points_cam, K, size, true_points, lengths, min_depth):
    """Brute-force numpy l_dist for one pair."""
    h = points_cam @ K.T
    keep = h[:, 2] > min_depth
    uv = h[keep, :2] / h[keep, 2:]
    tp = true_points[:lengths]
    scale = 1.0 / max(size)
    d = ((uv[:, None] - tp[None]) ** 2).sum(-1) * scale**2
    return d.min(1).mean() + d.min(0).mean()


def test_chamfer_loss_matches_brute_force_with_padding_and_points_behind_the_camera():
    gen = torch.Generator().manual_seed(3)
    P, N, M = 3, 40, 25
    points = torch.randn(P, N, 3, generator=gen, dtype=DT) * 0.5 + torch.tensor([0.0, 0.0, 1.5], dtype=DT)
    points[:, :5, 2] = -1.0  # behind the camera: excluded
    true = torch.rand(P, M, 2, generator=gen, dtype=DT) * torch.tensor([80.0, 60.0], dtype=DT)
    lengths = torch.tensor([25, 10, 1])
    sizes = torch.tensor([[60, 80], [60, 80], [120, 40]])
    loss = silhouette_chamfer_loss(points, K.expand(P, 3, 3), sizes, true, lengths, min_depth=0.01)
    for p in range(P):
        expected = _oracle_chamfer(
            points[p].numpy(), K.numpy(), sizes[p].tolist(), true[p].numpy(), int(lengths[p]), 0.01
        )
        assert loss[p].item() == pytest.approx(expected, rel=1e-10)


def test_chamfer_loss_is_resolution_independent_and_zero_for_undefined_pairs():
    gen = torch.Generator().manual_seed(4)
    points = torch.randn(2, 30, 3, generator=gen, dtype=DT) * 0.3 + torch.tensor([0.0, 0.0, 2.0], dtype=DT)
    true = torch.rand(2, 20, 2, generator=gen, dtype=DT) * 60
    base = silhouette_chamfer_loss(points, K, (60, 80), true)
    doubled = silhouette_chamfer_loss(points, scale_intrinsics(K, 2.0, 2.0), (120, 160), true * 2)
    torch.testing.assert_close(base, doubled)
    behind = points.clone()
    behind[0, :, 2] = -1.0
    loss = silhouette_chamfer_loss(behind, K, (60, 80), true, torch.tensor([20, 0]))
    assert loss.tolist() == [0.0, 0.0]


def test_chamfer_loss_gradcheck():
    gen = torch.Generator().manual_seed(5)
    points = (
        torch.randn(2, 7, 3, generator=gen, dtype=DT) * 0.3 + torch.tensor([0.0, 0.0, 2.0], dtype=DT)
    ).requires_grad_()
    true = torch.rand(2, 6, 2, generator=gen, dtype=DT) * 60
    lengths = torch.tensor([6, 3])
    assert torch.autograd.gradcheck(lambda p: silhouette_chamfer_loss(p, K, (60, 80), true, lengths), (points,))


def test_bce_values_iou_gate_and_valid_cells():
    soft = torch.full((2, 6, 6), 0.2, dtype=DT)
    soft[:, 1:5, 1:5] = 0.9  # predicted square, 16 cells
    true = torch.zeros(2, 6, 6, dtype=DT)
    true[0, 1:5, 1:5] = 1.0  # identical: IoU 1
    true[1, 1:5, 3:6] = 1.0  # 12 cells, overlap 8: IoU 8 / 20
    out = silhouette_bce_loss(soft.requires_grad_(), true)
    expected = -(true * soft.log() + (1 - true) * (1 - soft).log()).flatten(1).mean(1)
    torch.testing.assert_close(out.loss, expected)
    torch.testing.assert_close(out.iou, torch.tensor([1.0, 0.4], dtype=DT))
    assert out.gate.tolist() == [True, False] and not out.iou.requires_grad
    valid = torch.zeros(2, 6, 6, dtype=torch.bool)
    valid[:, :, :4] = True  # only the left 4 columns were observed
    masked = silhouette_bce_loss(soft, true, valid)
    torch.testing.assert_close(masked.loss, _masked_mean(soft, true, valid))
    torch.testing.assert_close(masked.iou, torch.tensor([1.0, 4 / 12], dtype=DT))
    combined = l2d_loss(torch.tensor([0.5, 0.25], dtype=DT), out)
    torch.testing.assert_close(combined, torch.stack([0.5 + out.loss[0], torch.tensor(0.25, dtype=DT)]))
    with pytest.raises(ValueError, match="one shape"):
        silhouette_bce_loss(soft, true[:, :5])


def _masked_mean(soft, true, valid):
    per = -(true * soft.log() + (1 - true) * (1 - soft).log())
    return torch.stack([per[i][valid[i]].mean() for i in range(len(per))])


def test_bce_diagnostics_leave_out_the_log_clamp_and_count_unreached_true_pixels():
    """BCE clamps log(0) to -100: true pixels that no face reaches (soft exactly 0) add 100 each
    and no gradient. ``loss_reached`` is the mean over the other cells, ``unreached`` the share of
    true (coverage-weighted) pixels with soft == 0; computed here directly in numpy."""
    gen = torch.Generator().manual_seed(3)
    soft = torch.rand(3, 8, 8, generator=gen, dtype=DT) * 0.98 + 0.01
    soft[:, :, 6:] = 0.0  # no face reaches the two right columns
    soft[2, 0, 0] = 1.0  # fully covered cell where the truth is empty: log(1 - 1) is clamped too
    true = (torch.rand(3, 8, 8, generator=gen) > 0.4).to(DT)
    true[1, 2, 2] = 0.5  # fractional coverage
    true[2, 0, 0] = 0.0
    valid = torch.ones(3, 8, 8, dtype=torch.bool)
    valid[0, 7] = False
    out = silhouette_bce_loss(soft, true, valid)
    s, t, v = soft.numpy(), true.numpy(), valid.numpy()
    for p in range(3):
        with np.errstate(divide="ignore", invalid="ignore"):
            per = -(t[p] * np.log(s[p]) + (1 - t[p]) * np.log(1 - s[p]))
        clamped = ((s[p] == 0) & (t[p] > 0)) | ((s[p] == 1) & (t[p] < 1))
        keep = v[p] & ~clamped
        assert out.loss_reached[p].item() == pytest.approx(np.nan_to_num(per)[keep].mean(), rel=1e-9)
        true_mass = (t[p] * v[p]).sum()
        assert out.unreached[p].item() == pytest.approx((t[p] * v[p] * (s[p] == 0)).sum() / true_mass, rel=1e-9)
    assert (out.loss > out.loss_reached).all()  # the clamp mass is in the plain l_xent only


def test_bce_diagnostics_take_summed_area_rounding_for_exact_coverage():
    """Window cells the mask does not reach get coverage ~1e-14 from the summed-area table's float64
    rounding (which cells, depends on the CPU's vector unit): cells with no face there are not
    clamped, and a mask cell's coverage 1 - 1e-14 under soft == 1 is not either."""
    soft = torch.full((1, 4, 4), 0.5, dtype=DT)
    soft[0, 0] = 0.0  # no face reaches the top row
    soft[0, 1, 0] = 1.0
    exact = torch.zeros(1, 4, 4, dtype=DT)
    exact[0, 1, 0] = 1.0
    rounded = exact.clone()
    rounded[0, 0] = 1e-14
    rounded[0, 1, 0] = 1 - 1e-14
    exact_out, rounded_out = silhouette_bce_loss(soft, exact), silhouette_bce_loss(soft, rounded)
    assert rounded_out.loss_reached.item() == pytest.approx(exact_out.loss_reached.item(), rel=1e-9)
    assert exact_out.loss_reached.item() == pytest.approx(math.log(2) * 11 / 16, rel=1e-9)  # all 16 kept
    real = exact.clone()
    real[0, 0, 0] = 1e-3  # a real sliver of mask under no face is clamped: one cell left out
    assert silhouette_bce_loss(soft, real).loss_reached.item() == pytest.approx(math.log(2) * 11 / 15, rel=1e-9)


def test_soft_iou_of_binary_silhouettes_is_pycocotools_iou_and_its_gradient_is_exact():
    """On 0/1 silhouettes 1 - soft_iou_loss is the masks' IoU (pycocotools' on RLE, restricted to the
    valid cells by zeroing the others in both); on soft values its gradient matches finite differences."""
    mask_utils = pytest.importorskip("pycocotools.mask")
    gen = torch.Generator().manual_seed(11)
    pred = torch.rand(3, 9, 7, generator=gen) > 0.5
    true = torch.rand(3, 9, 7, generator=gen) > 0.4
    valid = torch.ones(3, 9, 7, dtype=torch.bool)
    valid[1, :, 5:] = False  # cells outside the image
    loss = soft_iou_loss(pred.to(DT), true, valid)
    for p in range(3):
        rle = [mask_utils.encode(np.asfortranarray((m[p] & valid[p]).numpy().astype(np.uint8))) for m in (pred, true)]
        expected = mask_utils.iou([rle[0]], [rle[1]], [False])[0, 0]
        assert 1.0 - loss[p].item() == pytest.approx(expected, rel=1e-9)
    assert (
        soft_iou_loss(torch.zeros(1, 4, 4, dtype=DT), torch.zeros(1, 4, 4)).item() == 1.0
    )  # nothing to match: no credit
    soft = (torch.rand(2, 5, 5, generator=gen, dtype=DT) * 0.9 + 0.05).requires_grad_()
    target = torch.rand(2, 5, 5, generator=gen, dtype=DT)  # fractional coverage
    assert torch.autograd.gradcheck(lambda x: soft_iou_loss(x, target, valid[:2, :5, 2:7]), (soft,))  # masked cells too
