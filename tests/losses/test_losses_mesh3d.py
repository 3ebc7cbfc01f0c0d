"""Mesh R-CNN's 3D losses against independent oracles (scipy's cKDTree, trimesh's face normals)."""

import numpy as np
import torch
import trimesh
from scipy.spatial import cKDTree

from usl.geometry import Meshes, ico_sphere, sample_points_from_meshes
from usl.losses import chamfer_normal_loss


def _oracle(x, nx, y, ny):
    dist_xy, idx_xy = cKDTree(y).query(x)
    dist_yx, idx_yx = cKDTree(x).query(y)
    chamfer = (dist_xy**2).mean() + (dist_yx**2).mean()
    cos_xy = np.abs((nx * ny[idx_xy]).sum(1) / np.linalg.norm(nx, axis=1) / np.linalg.norm(ny[idx_xy], axis=1))
    cos_yx = np.abs((ny * nx[idx_yx]).sum(1) / np.linalg.norm(ny, axis=1) / np.linalg.norm(nx[idx_yx], axis=1))
    return chamfer, (1 - cos_xy).mean() + (1 - cos_yx).mean()


def test_chamfer_and_normal_terms_match_a_kdtree_oracle():
    rng = np.random.default_rng(0)
    x, y = rng.normal(size=(2, 300, 3)), rng.normal(size=(2, 200, 3)) + 0.3
    nx, ny = rng.normal(size=(2, 300, 3)), rng.normal(size=(2, 200, 3))
    out = chamfer_normal_loss(*(torch.from_numpy(a) for a in (x, nx, y, ny)))
    for b in range(2):
        chamfer, normals = _oracle(x[b], nx[b], y[b], ny[b])
        assert np.isclose(out.chamfer[b].item(), chamfer, rtol=1e-9)
        assert np.isclose(out.normals[b].item(), normals, rtol=1e-9)


def test_sampled_normals_are_the_faces_normals_of_trimesh():
    box = trimesh.creation.box(extents=(0.5, 1.0, 2.0))
    meshes = Meshes([torch.from_numpy(box.vertices).double()], [torch.from_numpy(box.faces)])
    points, normals = sample_points_from_meshes(meshes, 500, torch.Generator().manual_seed(0), return_normals=True)
    # the faces whose plane holds each point (two coplanar triangles per side of the box)
    offsets = np.einsum("pfk,fk->pf", points[0].numpy()[:, None] - box.vertices[box.faces[:, 0]], box.face_normals)
    holds = np.abs(offsets) < 1e-9
    assert (holds.sum(1) == 2).all()  # every point lies on exactly one side of the box
    expected = box.face_normals[holds.argmax(1)]
    np.testing.assert_allclose(normals[0].numpy(), expected, atol=1e-12)  # same winding: outward


def test_identical_meshes_score_near_zero_and_descent_approaches_the_target():
    verts, faces = ico_sphere(2)
    target = verts.double() * torch.tensor([0.6, 0.3, 0.4], dtype=torch.float64) + 0.1
    gen = lambda: torch.Generator().manual_seed(1)  # noqa: E731

    def loss(pred):
        p, pn = sample_points_from_meshes(
            Meshes.from_shared_topology(pred[None], faces), 2000, gen(), return_normals=True
        )
        t, tn = sample_points_from_meshes(
            Meshes.from_shared_topology(target[None], faces), 2000, gen(), return_normals=True
        )
        return chamfer_normal_loss(p, pn, t, tn)

    same = loss(target)
    assert same.chamfer.item() == 0.0 and same.normals.item() < 1e-12  # the same points and normals
    start = verts.double().clone()
    far = loss(start)
    assert far.chamfer.item() > 0.05 and far.normals.item() > 0.05
    pred = start.clone().requires_grad_(True)
    optimizer = torch.optim.Adam([pred], lr=0.01)
    for _ in range(30):
        optimizer.zero_grad()
        (loss(pred).chamfer.sum() + 0.1 * loss(pred).normals.sum()).backward()
        optimizer.step()
    after = loss(pred.detach())
    total = lambda terms: (terms.chamfer + 0.1 * terms.normals).item()  # noqa: E731
    assert after.chamfer.item() < 0.25 * far.chamfer.item() and total(after) < 0.25 * total(far)
