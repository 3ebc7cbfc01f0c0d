"""l_order: the true masks say which object is in front wherever two predicted meshes overlap.

True masks are visible parts, so they are disjoint: a pixel of object b's true mask shows b, and
any other object's mesh a that covers it must lie behind b's mesh there. The silhouette losses
render each object alone and cannot see this (a's spill onto b costs the same whatever the depth
order), while usl-eval draws all objects together and the nearest wins: a mesh in front of its
occluder steals the occluder's pixels. With true order the shipped ``tiny``'s held-out input views
score 66.3 Mask IoU instead of 48.5 (``scripts/mask_head_iou.py``).

For each pixel p of b's true mask covered by both meshes, where a's surface is not at least
``margin`` behind b's, l_order adds ``relu(d_b(p) - d_a(p) + margin)``; per object b the sum over
a and p is divided by b's true mask area. Depth d(p) is where p's ray meets the plane of the face
the z-buffer found there: exact, and differentiable in the vertices (like PyTorch3D's
``pix_to_face`` with re-interpolated depth); which face covers p carries no gradient. The order
is a relation of 2D annotations only, so this adds no 3D supervision.
"""
from __future__ import annotations

from typing import NamedTuple

import torch

Tensor = torch.Tensor


class OcclusionOrder(NamedTuple):
    """Per object (M,): ``loss`` as above, and ``stolen``, the fraction of its true mask that another
    mesh wins when all are z-buffered together (what usl-eval's Mask IoU loses to the order)."""

    loss: Tensor
    stolen: Tensor


def ray_plane_depth(tri: Tensor, px: Tensor, py: Tensor, K_inv: Tensor) -> Tensor:
    """Planar depth (camera z) where the rays through pixel coordinates (px, py) meet the planes of
    triangles ``tri`` (n, 3, 3) in the camera frame; differentiable in ``tri``."""
    rays = torch.stack([px, py, torch.ones_like(px)], -1) @ K_inv.transpose(-1, -2)
    normal = torch.linalg.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    denom = (normal * rays).sum(-1)
    tiny = torch.finfo(denom.dtype).eps
    denom = torch.where(denom.abs() < tiny, torch.full_like(denom, tiny), denom)  # edge-on faces
    return rays[:, 2] * (normal * tri[:, 0]).sum(-1) / denom


def occlusion_order_loss(
    verts: Tensor, faces: Tensor, face_map: Tensor, depth_map: Tensor, true_masks: Tensor, K: Tensor, margin: float
) -> OcclusionOrder:
    """l_order for the M objects of one view.

    Args:
        verts: (M, V, 3) each object's mesh in the view's camera frame (shared topology ``faces``).
        faces: (F, 3) long.
        face_map, depth_map: (M, H, W) each mesh rasterized alone: the index of its nearest face
            (-1 where it is absent) and that surface's depth (+inf where absent).
        true_masks: (M, H, W) bool visible masks, object by object.
        K: (3, 3) the view's intrinsics.
    """
    num_objects = verts.shape[0]
    covered = face_map >= 0
    area = true_masks.flatten(1).sum(1).clamp_min(1)
    # another mesh is nearer (amin: argmin over a leading dim is ~200x slower on CPU)
    won_by_other = depth_map > depth_map.amin(0)
    stolen = (true_masks & won_by_other).flatten(1).sum(1) / area
    # conflicts[a, b]: b's true pixels both meshes cover, with a not `margin` behind b
    conflicts = covered[:, None] & (covered & true_masks)[None] & (depth_map[:, None] < depth_map[None] + margin)
    conflicts &= ~torch.eye(num_objects, dtype=torch.bool, device=verts.device)[:, :, None, None]
    front, behind, row, col = torch.nonzero(conflicts, as_tuple=True)
    loss = verts.new_zeros(num_objects)
    if len(front):
        px, py = col.to(verts.dtype) + 0.5, row.to(verts.dtype) + 0.5  # pixel centres (DESIGN.md §2)
        K_inv = torch.linalg.inv(K.to(verts.dtype))

        def depth(objects: Tensor) -> Tensor:
            tri = verts[objects[:, None], faces[face_map[objects, row, col]]]
            return ray_plane_depth(tri, px, py, K_inv)

        hinge = torch.relu(depth(behind) - depth(front) + margin)
        loss = loss.index_add(0, behind, hinge)
    return OcclusionOrder(loss / area, stolen.to(verts.dtype))
