"""Ico-spheres, edges, uniform Laplacian and the packed Meshes structure (trimesh, numpy as oracles)."""

import numpy as np
import pytest
import torch
import trimesh

from usl.geometry.icosphere import ico_sphere
from usl.geometry.meshes import Meshes
from usl.geometry.topology import MeshTemplate, faces_on_each_edge, uniform_laplacian, unique_edges
from usl.utils.op_count import count_ops


@pytest.mark.parametrize("level", range(5))
def test_ico_sphere_counts_and_closed_consistent_surface(level):
    verts, faces = ico_sphere(level)
    num_v, num_f = 10 * 4**level + 2, 20 * 4**level
    assert verts.shape == (num_v, 3) and faces.shape == (num_f, 3) and faces.dtype == torch.int64
    edges = unique_edges(faces)
    assert edges.shape[0] == 3 * num_f // 2
    assert num_v - edges.shape[0] + num_f == 2  # Euler characteristic of a sphere
    torch.testing.assert_close(verts.norm(dim=1), torch.ones(num_v))
    mesh = trimesh.Trimesh(verts.double().numpy(), faces.numpy(), process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume > 0  # positive signed volume: normals point outward
    centroids = mesh.triangles_center
    assert (np.einsum("ij,ij->i", mesh.face_normals, centroids) > 0).all()


def test_ico_sphere_is_a_fresh_copy_in_the_requested_dtype():
    verts, _ = ico_sphere(1, dtype=torch.float64)
    verts.mul_(0)
    again, _ = ico_sphere(1, dtype=torch.float64)
    assert again.dtype == torch.float64 and again.norm(dim=1).min() > 0.99


def test_unique_edges_match_trimesh():
    box = trimesh.creation.box()
    edges = unique_edges(torch.from_numpy(box.faces))
    expected = {tuple(e) for e in np.sort(box.edges_unique, axis=1)}
    assert {tuple(e) for e in edges.tolist()} == expected and len(edges) == len(expected)
    assert (edges[:, 0] < edges[:, 1]).all()


def _grid(n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Flat regular n x n grid in the z=0 plane, every square split along the same diagonal."""
    ys, xs = torch.meshgrid(torch.arange(n, dtype=torch.float64), torch.arange(n, dtype=torch.float64), indexing="ij")
    verts = torch.stack([xs.flatten() * 0.3, ys.flatten() * 0.3, torch.zeros(n * n, dtype=torch.float64)], dim=1)
    i = torch.arange(n - 1)
    r, c = torch.meshgrid(i, i, indexing="ij")
    a = (r * n + c).flatten()
    faces = torch.cat([torch.stack([a, a + 1, a + n + 1], 1), torch.stack([a, a + n + 1, a + n], 1)])
    return verts, faces


def test_uniform_laplacian_of_flat_grid_vanishes_inside_only():
    n = 6
    verts, faces = _grid(n)
    L = uniform_laplacian(n * n, unique_edges(faces), dtype=torch.float64)
    lv = torch.sparse.mm(L, verts).norm(dim=1).view(n, n)
    assert lv[1:-1, 1:-1].abs().max() < 1e-12
    boundary = torch.ones(n, n, dtype=torch.bool)
    boundary[1:-1, 1:-1] = False
    assert (lv[boundary] > 1e-3).all()


def test_uniform_laplacian_matches_dense_oracle_from_trimesh_neighbours():
    mesh = trimesh.creation.icosphere(subdivisions=1)
    mesh.vertices[:, 0] *= 1.7  # not a symmetric shape
    L = uniform_laplacian(len(mesh.vertices), unique_edges(torch.from_numpy(mesh.faces)), torch.float64).to_dense()
    dense = np.eye(len(mesh.vertices))
    for i, nbrs in enumerate(mesh.vertex_neighbors):
        dense[i, nbrs] -= 1.0 / len(nbrs)
    np.testing.assert_allclose(L.numpy(), dense, atol=1e-12)
    # an isolated vertex gets an all-zero row
    L_iso = uniform_laplacian(4, torch.tensor([[0, 1], [1, 2]]), torch.float64).to_dense()
    assert (L_iso[3] == 0).all() and L_iso[1, 1] == 1 and L_iso[1, 0] == -0.5


def _mixed_meshes() -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    box = trimesh.creation.box()
    tet = trimesh.creation.icosphere(subdivisions=0)
    sphere_v, sphere_f = ico_sphere(1, dtype=torch.float64)
    verts = [torch.from_numpy(box.vertices), sphere_v, torch.from_numpy(tet.vertices) + 3.0]
    faces = [torch.from_numpy(box.faces), sphere_f, torch.from_numpy(tet.faces)]
    return verts, faces


def test_meshes_packing_and_index_maps():
    verts, faces = _mixed_meshes()
    meshes = Meshes(verts, faces)
    assert len(meshes) == 3 and meshes.shared_faces is None
    counts = [len(v) for v in verts]
    assert meshes.num_verts_per_mesh().tolist() == counts
    assert meshes.num_faces_per_mesh().tolist() == [len(f) for f in faces]
    torch.testing.assert_close(meshes.verts_packed(), torch.cat(verts))
    offsets = np.cumsum([0] + counts[:-1])
    expected_faces = torch.cat([f + int(o) for f, o in zip(faces, offsets, strict=True)])
    assert torch.equal(meshes.faces_packed(), expected_faces)
    assert meshes.verts_packed_to_mesh_idx().tolist() == sum(([i] * c for i, c in enumerate(counts)), [])
    assert meshes.faces_packed_to_mesh_idx().tolist() == sum(([i] * len(f) for i, f in enumerate(faces)), [])
    expected_edges = torch.cat([unique_edges(f) + int(o) for f, o in zip(faces, offsets, strict=True)])
    assert torch.equal(meshes.edges_packed(), expected_edges)
    assert meshes.num_edges_per_mesh().tolist() == [len(unique_edges(f)) for f in faces]
    for got, want in zip(meshes.faces_list(), faces, strict=True):
        assert torch.equal(got, want)
    for got, want in zip(meshes.verts_list(), verts, strict=True):
        assert torch.equal(got, want)
    padded = meshes.verts_padded()
    assert padded.shape == (3, max(counts), 3) and torch.equal(padded[2, : counts[2]], verts[2])
    dense_L = meshes.laplacian_packed().to_dense()
    for f, o, c in zip(faces, offsets, counts, strict=True):
        block = uniform_laplacian(c, unique_edges(f), torch.float64).to_dense()
        torch.testing.assert_close(dense_L[o : o + c, o : o + c], block)


def test_shared_topology_fast_path_equals_generic_path():
    sphere_v, sphere_f = ico_sphere(2)
    batch = torch.stack([sphere_v, sphere_v * 2 + 1, sphere_v - 3])
    fast = Meshes.from_shared_topology(batch, sphere_f)
    from_lists = Meshes(list(batch), [sphere_f.clone() for _ in range(3)])  # equal faces are detected
    generic = Meshes(list(batch), [sphere_f, sphere_f, sphere_f[[1, 0] + list(range(2, len(sphere_f)))]])
    assert fast.shared_faces is not None and from_lists.shared_faces is not None and generic.shared_faces is None
    for other in (from_lists, generic):
        assert torch.equal(fast.verts_packed(), other.verts_packed())
        assert torch.equal(fast.edges_packed(), other.edges_packed())
        assert torch.equal(fast.verts_packed_to_mesh_idx(), other.verts_packed_to_mesh_idx())
        assert torch.equal(fast.num_edges_per_mesh(), other.num_edges_per_mesh())
    assert torch.equal(fast.faces_packed(), torch.cat([sphere_f + i * len(sphere_v) for i in range(3)]))
    assert fast.verts_padded().data_ptr() == fast.verts_packed().data_ptr()  # a view, no copy
    assert all(f is sphere_f or torch.equal(f, sphere_f) for f in fast.faces_list())


def test_a_mesh_template_gives_the_same_edges_with_no_device_read():
    sphere_v, sphere_f = ico_sphere(2)
    template = MeshTemplate.build(sphere_f, len(sphere_v))
    assert torch.equal(template.edges, unique_edges(sphere_f)) and torch.equal(
        template.edge_faces, faces_on_each_edge(sphere_f)
    )
    batch = torch.stack([sphere_v, sphere_v * 2 + 1, sphere_v - 3])
    with count_ops() as count:
        edges = Meshes.from_shared_topology(batch, sphere_f, template.edges).edges_packed()
        laplacian = Meshes.from_shared_topology(batch, sphere_f, template.edges).laplacian_packed()
    assert count.syncs.get("unique", 0) == 0, count.syncs
    reference = Meshes.from_shared_topology(batch, sphere_f)
    assert torch.equal(edges, reference.edges_packed())
    assert torch.equal(laplacian.to_dense(), reference.laplacian_packed().to_dense())


def test_offset_and_update_keep_topology_and_gradients():
    sphere_v, sphere_f = ico_sphere(1)
    meshes = Meshes.from_shared_topology(sphere_v.expand(2, -1, -1).clone(), sphere_f)
    edges = meshes.edges_packed()
    offsets = torch.randn(meshes.verts_packed().shape, requires_grad=True)
    moved = meshes.offset_verts(offsets)
    assert moved.edges_packed() is edges  # cached topology is shared, not rebuilt
    torch.testing.assert_close(moved.verts_packed(), meshes.verts_packed() + offsets)
    moved.verts_packed().sum().backward()
    assert torch.equal(offsets.grad, torch.ones_like(offsets))
    replaced = meshes.update_packed(torch.zeros_like(meshes.verts_packed()))
    assert replaced.verts_packed().abs().sum() == 0 and len(replaced) == 2
    with pytest.raises(ValueError, match="update_packed"):
        meshes.update_packed(torch.zeros(5, 3))
    assert meshes.to("cpu").verts_packed().device.type == "cpu"


def test_meshes_reject_bad_input():
    v, f = ico_sphere(0)
    with pytest.raises(ValueError, match="index outside"):
        Meshes([v], [f + 1])
    with pytest.raises(ValueError, match="integer"):
        Meshes([v], [f.float()])
    with pytest.raises(ValueError, match="verts of mesh 1"):
        Meshes([v, v[:, :2]], [f, f])
    with pytest.raises(ValueError, match="2 vertex tensors but 1"):
        Meshes([v, v], [f])
