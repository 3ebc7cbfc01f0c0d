"""Shape regularizers of the paper's appendix (edge length, L2 on offsets, Laplacian), and normal consistency."""

from __future__ import annotations

import torch

from usl.geometry.meshes import Meshes

Tensor = torch.Tensor


def _per_mesh(values: Tensor, mesh_idx: Tensor, num_meshes: int) -> Tensor:
    """The mean of ``values`` within each mesh: (num_meshes,), 0 for meshes without entries."""
    sums = values.new_zeros(num_meshes).index_add(0, mesh_idx, values)
    # index_add, not bincount: bincount's output size is read from the device
    counts = values.new_zeros(num_meshes).index_add(0, mesh_idx, torch.ones_like(values)).clamp(min=1)
    return sums / counts


def _mean_over_meshes(per_mesh: Tensor) -> Tensor:
    """The mean over meshes; an empty batch gives a zero that is still connected to the graph."""
    return per_mesh.sum() * 0.0 if per_mesh.numel() == 0 else per_mesh.mean()


def edge_length_per_mesh(meshes: Meshes) -> Tensor:
    """Each mesh's mean squared edge length over its unique undirected edges: (N,)."""
    edges = meshes.edges_packed()
    verts = meshes.verts_packed()
    sq_len = (verts[edges[:, 0]] - verts[edges[:, 1]]).pow(2).sum(dim=1)
    return _per_mesh(sq_len, meshes.edges_packed_to_mesh_idx(), len(meshes))


def mesh_edge_loss(meshes: Meshes) -> Tensor:
    """L_edge of Mesh R-CNN: squared edge length, averaged per mesh, then over meshes.

    Uses the unique undirected edges (``Meshes.edges_packed``), like PyTorch3D's
    ``mesh_edge_loss`` with target length 0.
    """
    return _mean_over_meshes(edge_length_per_mesh(meshes))


def offset_l2_loss(offsets: Tensor) -> Tensor:
    """½‖dV‖²: half the squared norm of each vertex offset, averaged over vertices.

    Pass the PRE-tanh offsets (..., 3), packed (sum V, 3) or padded (B, V, 3); with the
    model's identical ico-sphere per object every mesh has as many vertices, so the plain
    mean equals the mean of per-mesh means. No offsets (no objects) give 0.
    """
    if offsets.numel() == 0:
        return offsets.sum() * 0.0
    return offset_l2_per_mesh(offsets).mean()


def offset_l2_per_mesh(offsets: Tensor) -> Tensor:
    """½‖dV‖² averaged over each mesh's vertices: (..., V, 3) offsets give (...,)."""
    return 0.5 * offsets.pow(2).sum(dim=-1).mean(dim=-1)


def laplacian_smoothing_loss(meshes: Meshes) -> Tensor:
    """L_laplac: ‖(L V)_i‖ per vertex with the uniform Laplacian, averaged per mesh, then over meshes.

    ``(L V)_i = v_i - mean(neighbours of v_i)`` (``uniform_laplacian``), as PyTorch3D's
    ``mesh_laplacian_smoothing(method="uniform")``.
    """
    return _mean_over_meshes(laplacian_per_mesh(meshes))


def laplacian_per_mesh(meshes: Meshes) -> Tensor:
    """Each mesh's mean ‖(L V)_i‖ (see :func:`laplacian_smoothing_loss`): (N,)."""
    lap = torch.sparse.mm(meshes.laplacian_packed(), meshes.verts_packed())
    return _per_mesh(torch.linalg.vector_norm(lap, dim=1), meshes.verts_packed_to_mesh_idx(), len(meshes))


def normal_consistency(verts: Tensor, faces: Tensor, pairs: Tensor) -> Tensor:
    """Mean ``1 - cos`` between the normals of the two faces on each edge, per mesh: (N,).

    ``verts`` (N, V, 3) share ``faces`` (F, 3); ``pairs`` (E, 2) are the faces on each edge
    (``faces_on_each_edge``). PyTorch3D's ``mesh_normal_consistency``: 0 on a plane, small on a
    fine smooth mesh, large where the mesh folds or spikes, however it is stretched.
    """
    corners = verts[:, faces]
    normals = torch.nn.functional.normalize(
        torch.cross(corners[:, :, 1] - corners[:, :, 0], corners[:, :, 2] - corners[:, :, 0], dim=-1), dim=-1
    )
    return (1.0 - (normals[:, pairs[:, 0]] * normals[:, pairs[:, 1]]).sum(dim=-1)).mean(dim=1)
