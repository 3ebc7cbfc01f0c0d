"""Shape regularizers (numpy / trimesh oracles, float64 gradcheck) and the weighted objective."""

import numpy as np
import pytest
import torch
import trimesh

from usl.config import load_config
from usl.geometry.icosphere import ico_sphere
from usl.geometry.meshes import Meshes
from usl.geometry.sampling import sample_points_from_meshes
from usl.geometry.topology import MeshTemplate, faces_on_each_edge
from usl.losses.regularizers import (
    laplacian_smoothing_loss,
    mesh_edge_loss,
    normal_consistency,
    offset_l2_loss,
)
from usl.losses.total import LossWeights, combine_losses

DT = torch.float64


def _two_meshes(seed: int = 0) -> tuple[list[trimesh.Trimesh], Meshes]:
    rng = np.random.default_rng(seed)
    a = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    b = trimesh.creation.icosphere(subdivisions=1)
    b.vertices = b.vertices * rng.uniform(0.5, 1.5, size=b.vertices.shape)
    meshes = Meshes([torch.from_numpy(m.vertices.copy()) for m in (a, b)], [torch.from_numpy(m.faces) for m in (a, b)])
    return [a, b], meshes


def test_edge_loss_is_mean_squared_edge_length_per_mesh_then_over_meshes():
    tms, meshes = _two_meshes()
    per_mesh = [
        np.mean(np.sum((m.vertices[m.edges_unique[:, 0]] - m.vertices[m.edges_unique[:, 1]]) ** 2, 1)) for m in tms
    ]
    assert mesh_edge_loss(meshes).item() == pytest.approx(np.mean(per_mesh), rel=1e-12)


def test_laplacian_loss_matches_dense_oracle():
    tms, meshes = _two_meshes(1)
    per_mesh = []
    for m in tms:
        lap = np.array([m.vertices[i] - m.vertices[n].mean(0) for i, n in enumerate(m.vertex_neighbors)])
        per_mesh.append(np.linalg.norm(lap, axis=1).mean())
    assert laplacian_smoothing_loss(meshes).item() == pytest.approx(np.mean(per_mesh), rel=1e-12)
    v, f = ico_sphere(2, dtype=DT)
    flat = Meshes.from_shared_topology(v[None] * 0, f)
    assert laplacian_smoothing_loss(flat).item() == 0.0


def test_offset_l2_is_half_squared_norm_averaged_over_vertices():
    offsets = torch.tensor([[[3.0, 4.0, 0.0], [0.0, 0.0, 0.0]], [[1.0, 0.0, 0.0], [0.0, 2.0, 0.0]]], dtype=DT)
    assert offset_l2_loss(offsets).item() == pytest.approx(0.5 * (25 + 0 + 1 + 4) / 4)
    assert offset_l2_loss(offsets.reshape(-1, 3)).item() == pytest.approx(offset_l2_loss(offsets).item())


def test_regularizers_gradcheck():
    v, f = ico_sphere(0, dtype=DT)
    gen = torch.Generator().manual_seed(2)
    verts = (v.repeat(2, 1) + 0.1 * torch.randn(24, 3, generator=gen, dtype=DT)).requires_grad_()
    template = Meshes.from_shared_topology(v.expand(2, -1, -1).clone(), f)
    assert torch.autograd.gradcheck(lambda x: mesh_edge_loss(template.update_packed(x)), (verts,))
    assert torch.autograd.gradcheck(lambda x: laplacian_smoothing_loss(template.update_packed(x)), (verts,))
    assert torch.autograd.gradcheck(offset_l2_loss, (verts,))


def test_normal_consistency_matches_trimesh_face_adjacency_angles_and_gradcheck():
    rng = np.random.default_rng(3)
    sphere = trimesh.creation.icosphere(subdivisions=2)
    bumpy = sphere.copy()
    bumpy.vertices = bumpy.vertices * rng.uniform(0.7, 1.3, size=(len(bumpy.vertices), 1)) * [1.5, 0.6, 1.0]
    faces = torch.from_numpy(sphere.faces)
    pairs = faces_on_each_edge(faces)
    assert sorted(map(tuple, pairs.sort(dim=1).values.tolist())) == sorted(
        map(tuple, np.sort(sphere.face_adjacency, axis=1).tolist())
    )
    verts = torch.from_numpy(np.stack([sphere.vertices, bumpy.vertices]))
    for mesh, value in zip((sphere, bumpy), normal_consistency(verts, faces, pairs).tolist(), strict=True):
        assert value == pytest.approx(np.mean(1.0 - np.cos(mesh.face_adjacency_angles)), abs=1e-9)
    v, f = ico_sphere(0, dtype=DT)
    x = (v + 0.1 * torch.randn(12, 3, generator=torch.Generator().manual_seed(4), dtype=DT))[None].requires_grad_()
    assert torch.autograd.gradcheck(lambda y: normal_consistency(y, f, faces_on_each_edge(f)), (x,))


def test_the_recipes_carry_the_papers_weights():
    """The paper's Appendix B-D: Scene-Shapes L_3D + 0.1 L_edge (no L_2D); Hypersim L_2D + L_3D + 0.05 ½‖dV‖²;
    ScanNet that + 0.1 L_laplac."""
    papers = {
        "scene_shapes": dict(mu_2d=0.0, mu_3d=1.0, edge=0.1, offset_l2=0.0, laplacian=0.0),
        "hypersim": dict(mu_2d=1.0, mu_3d=1.0, edge=0.0, offset_l2=0.05, laplacian=0.0),
        "scannet": dict(mu_2d=1.0, mu_3d=1.0, edge=0.0, offset_l2=0.05, laplacian=0.1),
    }
    for recipe, weights in papers.items():
        assert load_config(recipe).loss.weights == LossWeights(**weights, normal=0.0, dist=1.0, soft_iou=0.0), recipe


def test_combination():
    one = torch.tensor(1.0)
    scannet = load_config("scannet").loss.weights
    total, parts = combine_losses(
        scannet,
        l3d=2 * one,
        detection={"cls": one, "box": one},
        offset_l2=10 * one,
        laplacian=3 * one,
    )
    assert total.item() == pytest.approx(1 + 1 + 2 + 0.05 * 10 + 0.1 * 3)
    assert set(parts) == {"det/cls", "det/box", "l3d", "offset_l2", "laplacian"}
    total, parts = combine_losses(load_config("scene_shapes").loss.weights, l3d=one, edge=4 * one)
    assert total.item() == pytest.approx(1 + 0.4) and set(parts) == {"l3d", "edge"}
    doubled = LossWeights(mu_3d=2.0)
    total, _ = combine_losses(doubled, l3d=one, detection={}, offset_l2=one)
    assert total.item() == pytest.approx(2 + 0.05)
    with pytest.raises(ValueError, match="laplacian"):
        combine_losses(scannet, l3d=one, detection={}, offset_l2=one)
    with pytest.raises(ValueError, match="detection"):
        combine_losses(LossWeights(), l3d=one, offset_l2=one)
    total, parts = combine_losses(LossWeights(mu_2d=0.0, offset_l2=0.0, normal=0.2), l3d=one, normal=3 * one)
    assert total.item() == pytest.approx(1 + 0.6) and set(parts) == {"l3d", "normal"}
    with pytest.raises(ValueError, match="normal"):
        combine_losses(LossWeights(mu_2d=0.0, offset_l2=0.0, normal=0.2), l3d=one)


def test_an_image_without_objects_gives_zero_regularizers_and_no_samples():
    _, faces = ico_sphere(1)
    verts = torch.zeros(0, 42, 3, requires_grad=True)
    empty = Meshes.from_shared_topology(verts, faces)
    for loss in (
        mesh_edge_loss(empty),
        laplacian_smoothing_loss(empty),
        offset_l2_loss(verts),
    ):
        assert loss.item() == 0.0 and loss.requires_grad
    assert sample_points_from_meshes(empty, 10).shape == (0, 10, 3)


def test_the_model_averages_each_regularizer_per_image_then_over_the_batch_and_skips_unweighted_ones():
    from usl.model.multiview_loss import shape_regularizers

    v, faces = ico_sphere(1)
    verts = v * torch.tensor([[1.0, 0.5, 2.0]]) + 0.05 * torch.randn(
        3, 42, 3, generator=torch.Generator().manual_seed(5)
    )
    out = shape_regularizers(
        verts, [], MeshTemplate.build(faces, 42), [2, 0, 1], {"normal": True, "edge": True, "laplacian": True}
    )
    per_mesh = normal_consistency(verts, faces, faces_on_each_edge(faces))
    assert out["normal"].item() == pytest.approx(((per_mesh[0] + per_mesh[1]) / 2 + per_mesh[2]).item() / 3)
    edge = [mesh_edge_loss(Meshes.from_shared_topology(verts[rows], faces)) for rows in (slice(0, 2), slice(2, 3))]
    assert out["edge"].item() == pytest.approx((edge[0] + edge[1]).item() / 3)
    lap = [
        laplacian_smoothing_loss(Meshes.from_shared_topology(verts[rows], faces)) for rows in (slice(0, 2), slice(2, 3))
    ]
    assert out["laplacian"].item() == pytest.approx((lap[0] + lap[1]).item() / 3)
    assert out["offset_l2"] is None


def shape_regularizers_per_image(verts_cube, offsets, template, counts, need):
    """Per-image reference of ``shape_regularizers``: one Meshes and one term per image, summed image by image."""
    zero = verts_cube.sum() * 0.0
    result = {name: (zero.clone() if need.get(name) else None) for name in ("edge", "offset_l2", "laplacian", "normal")}
    starts = [0, *np.cumsum(counts).tolist()]
    batch = len(counts)
    for index in range(batch):
        rows = slice(starts[index], starts[index + 1])
        if starts[index + 1] == starts[index]:
            continue
        meshes = Meshes.from_shared_topology(verts_cube[rows].float(), template.faces, template.edges)
        if need.get("edge"):
            result["edge"] = result["edge"] + mesh_edge_loss(meshes) / batch
        if need.get("laplacian"):
            result["laplacian"] = result["laplacian"] + laplacian_smoothing_loss(meshes) / batch
        if need.get("normal"):
            per_mesh = normal_consistency(verts_cube[rows].float(), template.faces, template.edge_faces)
            result["normal"] = result["normal"] + per_mesh.mean() / batch
        if need.get("offset_l2"):
            result["offset_l2"] = result["offset_l2"] + sum(offset_l2_loss(o[rows]) for o in offsets) / batch
    return result


@pytest.mark.parametrize("counts", [[2, 0, 3, 1], [0, 0], [4]])
def test_batched_regularizers_equal_the_per_image_loop_in_values_and_gradients(counts):
    from usl.model.multiview_loss import shape_regularizers

    v, faces = ico_sphere(1)
    template = MeshTemplate.build(faces, len(v))
    g = torch.Generator().manual_seed(sum(counts))
    n = sum(counts)
    verts = v * torch.tensor([1.0, 0.5, 2.0]) + 0.05 * torch.randn(n, len(v), 3, generator=g)
    offsets = [torch.randn(n, len(v), 3, generator=g) for _ in range(2)]
    need = dict.fromkeys(("edge", "offset_l2", "laplacian", "normal"), True)
    results = []
    for regularizers in (shape_regularizers, shape_regularizers_per_image):
        leaves = [t.clone().requires_grad_(True) for t in (verts, *offsets)]
        out = regularizers(leaves[0], leaves[1:], template, counts, need)
        sum(out.values()).backward()
        results.append((out, [leaf.grad for leaf in leaves]))
    (new, new_grads), (old, old_grads) = results
    for name in need:
        torch.testing.assert_close(new[name], old[name], rtol=1e-6, atol=1e-7)
    for a, b in zip(new_grads, old_grads, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-7)
