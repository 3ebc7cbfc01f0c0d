"""Surface sampling (trimesh proximity as oracle) and chunked nearest neighbours (scipy cKDTree)."""

import importlib
import math

import numpy as np
import pytest
import torch
import trimesh
from scipy.spatial import cKDTree

from usl.geometry.icosphere import ico_sphere
from usl.geometry.meshes import Meshes
from usl.geometry.nearest import chamfer_directions, nearest_neighbors
from usl.geometry.sampling import face_areas_packed, sample_points_from_meshes, sample_points_in_groups
from usl.utils import compiled

NEAREST = importlib.import_module("usl.geometry.nearest")


def _distance_to_surface(mesh: trimesh.Trimesh, points: np.ndarray) -> np.ndarray:
    """Brute-force point-to-mesh distance with trimesh's point-triangle routine (no rtree needed)."""
    tris = np.repeat(mesh.triangles[None], len(points), 0).reshape(-1, 3, 3)
    reps = np.repeat(points, len(mesh.faces), 0)
    closest = trimesh.triangles.closest_point(tris, reps)
    return np.linalg.norm(closest - reps, axis=1).reshape(len(points), -1).min(1)


def test_samples_lie_on_each_mesh_surface():
    box = trimesh.creation.box(extents=(1.0, 2.0, 0.5))
    torus = trimesh.creation.torus(major_radius=1.0, minor_radius=0.3, major_sections=16, minor_sections=8)
    meshes = Meshes(
        [torch.from_numpy(box.vertices), torch.from_numpy(torus.vertices)],
        [torch.from_numpy(box.faces), torch.from_numpy(torus.faces)],
    )
    points = sample_points_from_meshes(meshes, 2000, generator=torch.Generator().manual_seed(0))
    assert points.shape == (2, 2000, 3) and points.dtype == torch.float64
    for mesh, pts in zip((box, torus), points.numpy(), strict=True):
        assert _distance_to_surface(mesh, pts[:500]).max() < 1e-9
    # box samples cover every side in proportion to its area (2x1, 2x0.5, 1x0.5 pairs)
    on_side = np.abs(np.abs(points[0].numpy()) - np.array([0.5, 1.0, 0.25])) < 1e-9
    fractions = on_side.mean(0)
    np.testing.assert_allclose(fractions, np.array([1.0, 0.5, 2.0]) / 3.5, atol=0.04)


def test_face_choice_follows_area_ratio_one_to_three():
    verts = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [5, 0, 0], [8, 0, 0], [5, 2, 0]], dtype=torch.float64)
    faces = torch.tensor([[0, 1, 2], [3, 4, 5]])  # areas 0.5 and 3.0 ... scaled below to 1:3
    verts[5, 1] = 1.0  # second face area = 1.5 = 3 x 0.5
    meshes = Meshes([verts], [faces])
    torch.testing.assert_close(face_areas_packed(meshes), torch.tensor([0.5, 1.5], dtype=torch.float64))
    n = 40000
    points = sample_points_from_meshes(meshes, n, generator=torch.Generator().manual_seed(1))[0]
    in_first = points[:, 0] <= 1.0
    first = in_first.double().mean().item()
    assert abs(first - 0.25) < 4 * math.sqrt(0.25 * 0.75 / n)
    # uniform inside a face: the corner triangle x + y < 1/2 holds a quarter of the face's area
    corner = (points[in_first, :2].sum(1) < 0.5).double().mean().item()
    assert abs(corner - 0.25) < 4 * math.sqrt(0.25 * 0.75 / in_first.sum().item())


def test_shared_topology_sampling_batches_and_is_reproducible():
    v, f = ico_sphere(2, dtype=torch.float64)
    scales = torch.tensor([1.0, 2.0, 0.5], dtype=torch.float64)
    meshes = Meshes.from_shared_topology(v[None] * scales[:, None, None], f)
    a = sample_points_from_meshes(meshes, 500, generator=torch.Generator().manual_seed(3))
    b = sample_points_from_meshes(meshes, 500, generator=torch.Generator().manual_seed(3))
    assert torch.equal(a, b)
    radii = a.norm(dim=-1)
    # flat faces sit slightly inside the sphere: radius within the chord sag of a level-2 sphere
    assert ((radii / scales[:, None]) > 0.97).all() and ((radii / scales[:, None]) <= 1.0 + 1e-12).all()


def test_gradient_flows_to_vertices():
    v, f = ico_sphere(0, dtype=torch.float64)
    verts = v.clone().requires_grad_()

    def sample(x):
        return sample_points_from_meshes(Meshes([x], [f]), 16, generator=torch.Generator().manual_seed(5))

    assert torch.autograd.gradcheck(sample, (verts,))
    sample(verts).sum().backward()
    # barycentric weights sum to one: d(sum of all coordinates)/d(vertex coords) totals #samples
    torch.testing.assert_close(verts.grad.sum(0), torch.full((3,), 16.0, dtype=torch.float64))


def test_nearest_neighbors_match_cKDTree_with_padding_and_small_chunks():
    gen = torch.Generator().manual_seed(0)
    x = torch.rand(3, 257, 3, generator=gen)
    y = torch.rand(3, 190, 3, generator=gen)
    valid = torch.arange(190)[None] < torch.tensor([190, 77, 1])[:, None]
    sq, idx = nearest_neighbors(x, y, valid, max_elements=3 * 190 * 10)  # chunks of 10 queries
    for b in range(3):
        dist, ref_idx = cKDTree(y[b, valid[b]].numpy()).query(x[b].numpy())
        np.testing.assert_allclose(sq[b].numpy(), dist**2, rtol=1e-5, atol=1e-7)
        assert (idx[b].numpy() == ref_idx).mean() > 0.99  # ties aside, the same neighbour


def test_chamfer_directions_masks_and_gradients():
    gen = torch.Generator().manual_seed(1)
    x = torch.rand(2, 6, 2, generator=gen, dtype=torch.float64, requires_grad=True)
    y = torch.rand(2, 5, 2, generator=gen, dtype=torch.float64, requires_grad=True)
    x_valid = torch.tensor([[True] * 6, [True, False] * 3])
    y_valid = torch.tensor([[True] * 5, [False] * 5])
    xy, yx = chamfer_directions(x, y, x_valid, y_valid)
    assert (xy[1] == 0).all() and (yx[1] == 0).all()  # batch 1 has no valid y: nothing defined
    brute = ((x[0, :, None] - y[0, None]) ** 2).sum(-1)
    torch.testing.assert_close(xy[0], brute.min(1).values)
    torch.testing.assert_close(yx[0], brute.min(0).values)
    assert torch.autograd.gradcheck(lambda a, b: chamfer_directions(a, b, x_valid, y_valid), (x, y))


def test_kdtree_backend_finds_the_same_neighbours_with_the_same_gradient():
    generator = torch.Generator().manual_seed(3)
    x = torch.rand(2, 400, 3, generator=generator, dtype=torch.float64, requires_grad=True)
    y = torch.rand(2, 300, 3, generator=generator, dtype=torch.float64)
    valid = torch.rand(2, 300, generator=generator) > 0.3
    results = {}
    for backend in ("torch", "kdtree"):
        sq, idx = nearest_neighbors(x, y, valid, backend=backend)
        (grad,) = torch.autograd.grad(sq.sum(), x)
        results[backend] = sq.detach(), idx, grad
    torch.testing.assert_close(results["torch"][0], results["kdtree"][0])
    assert torch.equal(results["torch"][1], results["kdtree"][1]) and valid.gather(1, results["kdtree"][1]).all()
    torch.testing.assert_close(results["torch"][2], results["kdtree"][2])


@pytest.mark.skipif(compiled.numba is None, reason="numba is not installed")
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_loop_backend_equals_the_torch_backend_and_exact_nearest_points(dtype):
    """Both directions against the torch backend (values and gradients) and a float64 argmin
    (first index on exact ties): invalid points both sides, duplicated points, a batch element
    without a valid candidate."""
    generator = torch.Generator().manual_seed(5)
    x = torch.rand(3, 70, 2, generator=generator, dtype=torch.float64)
    y = torch.rand(3, 50, 2, generator=generator, dtype=torch.float64)
    y[:, 25:] = y[:, :25]  # exact ties: the first of two equal points is the nearest
    x, y = x.to(dtype), y.to(dtype)
    x_valid = torch.rand(3, 70, generator=generator) > 0.2
    y_valid = torch.rand(3, 50, generator=generator) > 0.3
    y_valid[2] = False
    results = {}
    for backend in ("torch", "loop"):
        a, b = x.clone().requires_grad_(True), y.clone().requires_grad_(True)
        xy, yx = chamfer_directions(a, b, x_valid, y_valid, backend=backend)
        grad_x, grad_y = torch.autograd.grad((xy * 2).sum() + yx.sum(), (a, b))
        # the torch backend may pick either copy of a duplicated point: compare the copies' sum
        results[backend] = xy.detach(), yx.detach(), grad_x, grad_y[:, :25] + grad_y[:, 25:]
    for torch_result, loop_result in zip(results["torch"], results["loop"], strict=True):
        torch.testing.assert_close(loop_result, torch_result)
    exact = ((x[:, :, None].double() - y[:, None].double()) ** 2).sum(-1).masked_fill(~y_valid[:, None], np.inf)
    loop_idx = NEAREST._loop_indices(x, y, x_valid, y_valid)[0]
    assert torch.equal(loop_idx[:2], exact.argmin(2)[:2])
    twin_valid = y_valid[:2].gather(1, loop_idx[:2] % 25 + 25)
    assert ((loop_idx[:2] < 25) & twin_valid).any()  # ties were met, and went to the first point
    assert (results["loop"][0][2] == 0).all() and (results["loop"][1][2] == 0).all()


def test_sampling_in_groups_equals_one_call_per_group_with_its_generator():
    verts, faces = ico_sphere(1)
    g = torch.Generator().manual_seed(0)
    batch = verts * (1 + torch.rand(6, 1, 3, generator=g)) + torch.randn(6, 1, 3, generator=g)
    batch[4, :, 2] = 0.0  # a flat mesh among them
    sizes, seeds = [2, 3, 1], [11, 12, 13]
    grouped = sample_points_in_groups(
        Meshes.from_shared_topology(batch, faces), 50, sizes, [torch.Generator().manual_seed(s) for s in seeds], True
    )
    per_group = [
        sample_points_from_meshes(Meshes.from_shared_topology(part, faces), 50, torch.Generator().manual_seed(s), True)
        for part, s in zip(batch.split(sizes), seeds, strict=True)
    ]
    for got, expected in zip(grouped, zip(*per_group, strict=True), strict=True):
        assert torch.equal(got, torch.cat(expected))
    with pytest.raises(ValueError, match="groups"):
        sample_points_in_groups(Meshes.from_shared_topology(batch, faces), 5, [2, 3], [None, None])
