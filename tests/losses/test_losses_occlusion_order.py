"""l_order (``usl.losses.occlusion_order``): exact ray depths (trimesh's barycentrics as the oracle),
autograd against finite differences, and the hinge's behaviour on two spheres whose true masks say
which one is in front."""
import numpy as np
import pytest
import torch
import trimesh

from usl.geometry import ico_sphere
from usl.losses.occlusion_order import occlusion_order_loss, ray_plane_depth
from usl.render import rasterize_hard

DT = torch.float64
K = torch.tensor([[70.0, 0.0, 33.0], [0.0, 65.0, 30.0], [0.0, 0.0, 1.0]], dtype=DT)
SIZE = 64
MARGIN = 0.05


def _spheres(depth_a: float, depth_b: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Two ico-spheres overlapping in the image: a (radius 0.4) right of b (radius 0.5)."""
    verts, faces = ico_sphere(2)
    verts = verts.to(DT)
    return torch.stack([verts * 0.4 + torch.tensor([0.15, 0.0, depth_a], dtype=DT),
                        verts * 0.5 + torch.tensor([-0.15, 0.0, depth_b], dtype=DT)]), faces


def _alone(verts: torch.Tensor, faces: torch.Tensor):
    """Face and depth maps of each mesh rasterized alone (what l_order's caller provides)."""
    n = len(verts)
    packed = torch.cat(list(verts))
    packed_faces = torch.cat([faces + k * verts.shape[1] for k in range(n)])
    drawn = rasterize_hard(packed, packed_faces, torch.arange(n).repeat_interleave(len(faces)), K.expand(n, 3, 3),
                           SIZE, SIZE, mesh_view=torch.arange(n))
    return torch.where(drawn.face_map >= 0, drawn.face_map % len(faces), -1), drawn.depth_map


def _b_in_front_truth(verts, faces):
    """True visible masks of a scene where b occludes a: b's whole silhouette, a's remainder."""
    face_map, _ = _alone(verts, faces)
    silhouettes = face_map >= 0
    return torch.stack([silhouettes[0] & ~silhouettes[1], silhouettes[1]])


def test_ray_plane_depth_lies_on_the_pixels_face_and_equals_the_z_buffer():
    verts, faces = _spheres(2.5, 3.0)
    face_map, depth_map = _alone(verts, faces)
    rows, cols = torch.nonzero(face_map[1] >= 0, as_tuple=True)
    px, py = cols.to(DT) + 0.5, rows.to(DT) + 0.5
    tri = verts[1][faces[face_map[1, rows, cols]]]
    ours = ray_plane_depth(tri, px, py, torch.linalg.inv(K))
    rays = torch.stack([px, py, torch.ones_like(px)], -1) @ torch.linalg.inv(K).T
    points = (rays * (ours / rays[:, 2])[:, None]).numpy()
    # trimesh's barycentrics: the 3D point is in its face's plane (it is rebuilt exactly), inside it
    bary = trimesh.triangles.points_to_barycentric(tri.numpy(), points)
    np.testing.assert_allclose(trimesh.triangles.barycentric_to_points(tri.numpy(), bary), points, atol=1e-9)
    assert (bary > -1e-9).all()
    # and equals the rasterizer's perspective-correct depth (checked against PyTorch3D's)
    np.testing.assert_allclose(ours.numpy(), depth_map[1, rows, cols].numpy(), atol=1e-9)


def test_wrong_order_costs_and_its_gradient_matches_finite_differences():
    truth_verts, faces = _spheres(3.0, 2.5)  # truth: b nearer
    true = _b_in_front_truth(truth_verts, faces)
    verts, _ = _spheres(2.5, 3.0)  # predicted: a nearer, stealing b's pixels
    face_map, depth_map = _alone(verts, faces)
    out = occlusion_order_loss(verts, faces, face_map, depth_map, true, K, MARGIN)
    assert out.loss[0] == 0 and out.loss[1] > 0.1  # only b's true pixels are in conflict
    assert out.stolen[0] == 0 and 0.2 < out.stolen[1] < 0.9
    # with the z-buffer's faces fixed, l_order is smooth in the vertices: autograd = finite differences
    torch.autograd.gradcheck(
        lambda v: occlusion_order_loss(v, faces, face_map, depth_map, true, K, MARGIN).loss,
        (verts.clone().requires_grad_(),), eps=1e-6, atol=1e-6,
    )


def test_true_order_costs_nothing_unless_within_the_margin():
    verts, faces = _spheres(3.0, 2.5)
    true = _b_in_front_truth(verts, faces)
    out = occlusion_order_loss(verts, faces, *_alone(verts, faces), true, K, MARGIN)
    assert out.loss.abs().sum() == 0 and out.stolen.sum() == 0
    # a wholly behind b (radii 0.4 and 0.5: a's front at 3.1, b's back at 3.0), but by less than a
    # margin of 1: the hinge still asks for more, while the z-buffer already draws b in front
    close, _ = _spheres(3.5, 2.5)
    out = occlusion_order_loss(close, faces, *_alone(close, faces), _b_in_front_truth(close, faces), K, 1.0)
    assert out.loss[1] > 0 and out.stolen[1] == 0


def test_descending_l_order_on_depths_alone_restores_the_true_order():
    truth_verts, faces = _spheres(3.0, 2.5)
    true = _b_in_front_truth(truth_verts, faces)
    base, _ = _spheres(0.0, 0.0)
    depth = torch.tensor([2.5, 3.0], dtype=DT, requires_grad=True)  # a in front: wrong
    optimizer = torch.optim.SGD([depth], lr=0.5)
    stolen_before = None
    for _ in range(60):
        verts = base + torch.stack([torch.zeros_like(depth), torch.zeros_like(depth), depth], -1)[:, None]
        out = occlusion_order_loss(verts, faces, *_alone(verts.detach(), faces), true, K, MARGIN)
        stolen_before = out.stolen[1].item() if stolen_before is None else stolen_before
        if out.loss.sum() == 0:
            break
        optimizer.zero_grad()
        out.loss.sum().backward()
        optimizer.step()
    assert out.loss.sum() == 0 and depth[0] > depth[1]  # a now behind b
    assert stolen_before > 0.3 and out.stolen[1] < 0.1 * stolen_before
    # usl-eval's z-buffer of both meshes together gives b every true pixel its mesh covers (the few
    # still lost are where b's mesh, too far and so too small, does not reach: shape, not order)
    verts = verts.detach()
    face_map, _ = _alone(verts, faces)
    together = rasterize_hard(torch.cat(list(verts)), torch.cat([faces, faces + verts.shape[1]]),
                              torch.arange(2).repeat_interleave(len(faces)), K, SIZE, SIZE)
    assert together.masks[1][true[1] & (face_map[1] >= 0)].all()


@pytest.mark.parametrize("num_objects", [1, 3])
def test_no_overlap_no_loss(num_objects):
    verts, faces = ico_sphere(1)
    verts = torch.stack([verts.to(DT) * 0.2 + torch.tensor([x, 0.0, 3.0], dtype=DT) for x in (-1.0, 0.0, 1.0)[:num_objects]])
    face_map, depth_map = _alone(verts, faces)
    out = occlusion_order_loss(verts, faces, face_map, depth_map, face_map >= 0, K, MARGIN)
    assert out.loss.shape == (num_objects,) and out.loss.sum() == 0 and out.stolen.sum() == 0
