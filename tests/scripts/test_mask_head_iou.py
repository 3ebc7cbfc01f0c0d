"""scripts/experiments/mask_head_iou.py: the true-owner and true-object-order composites, against the z-buffer
of the same meshes placed in that order (two spheres overlapping in the image, drawn with both
depth orders), the count of rightly ordered pairs, and the owner oracle hiding a spill that no order hides."""

from __future__ import annotations

import mask_head_iou
import torch

from usl.geometry import ico_sphere

K = torch.tensor([[60.0, 0.0, 32.0], [0.0, 60.0, 32.0], [0.0, 0.0, 1.0]])


def _spheres(depth_a: float, depth_b: float) -> tuple[torch.Tensor, torch.Tensor]:
    """a and b of one radius, side by side, overlapping in the image, whatever their depths (a
    sphere scaled with its depth about the camera projects to the same disc)."""
    verts, faces = ico_sphere(2)
    return torch.stack(
        [
            (verts * 0.4 + torch.tensor([0.15, 0.0, 2.5])) * depth_a / 2.5,
            (verts * 0.4 + torch.tensor([-0.15, 0.0, 2.5])) * depth_b / 2.5,
        ]
    ), faces


def test_owner_wins_is_the_z_buffer_of_the_meshes_placed_in_the_true_order():
    b_in_front, faces = _spheres(3.0, 2.5)
    truth = mask_head_iou.draw(b_in_front, faces, K, 64, 64, together=True).masks  # b hides part of a
    a_in_front, _ = _spheres(2.5, 3.0)  # the same silhouettes, the wrong order
    wrong = mask_head_iou.draw(a_in_front, faces, K, 64, 64, together=True).masks
    alone = mask_head_iou.draw(a_in_front, faces, K, 64, 64, together=False)
    assert (wrong != truth).sum() > 50  # the order matters here
    torch.testing.assert_close(mask_head_iou.owner_wins_masks(alone.depth_map, truth), truth)
    # with the order the meshes already have, it is usl-eval's render of them
    torch.testing.assert_close(mask_head_iou.owner_wins_masks(alone.depth_map, wrong), wrong)


def test_true_object_order_is_the_z_buffer_of_the_meshes_placed_in_that_order():
    b_in_front, faces = _spheres(3.0, 2.5)
    truth = mask_head_iou.draw(b_in_front, faces, K, 64, 64, together=True).masks
    a_in_front, _ = _spheres(2.5, 3.0)
    alone = mask_head_iou.draw(a_in_front, faces, K, 64, 64, together=False)
    torch.testing.assert_close(mask_head_iou.object_order_masks(alone.depth_map, torch.tensor([3.0, 2.5])), truth)
    # an object without a true depth goes behind every other
    torch.testing.assert_close(
        mask_head_iou.object_order_masks(alone.depth_map, torch.tensor([float("nan"), 2.5])), truth
    )
    torch.testing.assert_close(
        mask_head_iou.object_order_masks(alone.depth_map, torch.tensor([2.5, float("nan")])),
        mask_head_iou.draw(a_in_front, faces, K, 64, 64, together=True).masks,
    )
    # the pair overlaps; its predicted order (a in front) is wrong for the truth (b in front)
    assert mask_head_iou.ordered_pairs(alone.masks, alone.nearest_depth, torch.tensor([3.0, 2.5])) == (0, 1)
    assert mask_head_iou.ordered_pairs(alone.masks, alone.nearest_depth, torch.tensor([2.5, 3.0])) == (1, 1)
    assert mask_head_iou.ordered_pairs(alone.masks, alone.nearest_depth, torch.tensor([2.5, float("nan")])) == (0, 0)


def test_the_owner_oracle_hides_a_spill_that_the_true_object_order_keeps():
    """b is in front, but its true mask is smaller than its mesh (the mesh spills onto a's visible
    pixels): drawn in the true order the spill takes a's pixels; the owner oracle gives them back."""
    meshes, faces = _spheres(3.0, 2.5)
    drawn = mask_head_iou.draw(meshes, faces, K, 64, 64, together=True).masks
    alone = mask_head_iou.draw(meshes, faces, K, 64, 64, together=False)
    spill = drawn[1] & (torch.arange(64)[None, :] > 34)  # b's pixels right of the middle: a's in truth
    truth = torch.stack([drawn[0] | spill, drawn[1] & ~spill])
    in_order = mask_head_iou.object_order_masks(alone.depth_map, torch.tensor([3.0, 2.5]))
    owner = mask_head_iou.owner_wins_masks(alone.depth_map, truth)
    assert spill.sum() > 20 and in_order[1][spill].all()  # the true order leaves the spill with b
    assert owner[0][spill].all() and not owner[1][spill].any()
