"""Area-weighted point sampling on mesh surfaces (for the 2D Chamfer loss and 3D metrics)."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from usl.geometry.meshes import Meshes

Tensor = torch.Tensor


def face_areas_packed(meshes: Meshes) -> Tensor:
    """(sum F_i,) triangle areas of all faces, differentiable w.r.t. the vertices."""
    v0, v1, v2 = meshes.verts_packed()[meshes.faces_packed()].unbind(1)
    return 0.5 * torch.linalg.vector_norm(torch.cross(v1 - v0, v2 - v0, dim=-1), dim=-1)


def _faces_padded(meshes: Meshes, values: Tensor) -> Tensor:
    """Scatter a per-face packed quantity into (B, max F_i), zero-padded."""
    if meshes.shared_faces is not None:
        return values.view(len(meshes), -1)
    counts = meshes.num_faces_per_mesh()
    first = torch.cumsum(counts, 0) - counts
    mesh_idx = meshes.faces_packed_to_mesh_idx()
    local = torch.arange(values.shape[0], device=values.device) - first[mesh_idx]
    out = values.new_zeros(len(meshes), int(counts.max()) if len(meshes) else 0)
    out[mesh_idx, local] = values
    return out


def sample_points_from_meshes(
    meshes: Meshes, num_samples: int, generator: torch.Generator | None = None, return_normals: bool = False
) -> Tensor | tuple[Tensor, Tensor]:
    """Sample points uniformly over each mesh's surface (area-weighted face choice + barycentric).

    Faces are drawn with probability proportional to their area (a non-differentiable
    choice), then a uniform point inside the face is taken with barycentric weights
    ``(1 - sqrt(r1), sqrt(r1) (1 - r2), sqrt(r1) r2)``; the points are differentiable
    w.r.t. the vertices. A mesh whose faces all have zero area draws faces uniformly.
    ``generator`` (on the meshes' device) makes the draw reproducible.

    Returns:
        (B, num_samples, 3) points, in the dtype and on the device of the vertices; with
        ``return_normals`` also (B, num_samples, 3) unit normals of the faces they lie on (by the
        faces' winding; zero on degenerate faces), for Mesh R-CNN's normal loss.
    """
    return sample_points_in_groups(meshes, num_samples, [len(meshes)], [generator], return_normals)


def sample_points_in_groups(
    meshes: Meshes,
    num_samples: int,
    group_sizes: Sequence[int],
    generators: Sequence[torch.Generator | None],
    return_normals: bool = False,
) -> Tensor | tuple[Tensor, Tensor]:
    """:func:`sample_points_from_meshes` of consecutive groups of meshes (``group_sizes``), group i
    drawing from ``generators[i]``: the same points as one call per group, with only the draws
    made group by group (e.g. the meshes of several samples, each sample keying its own draws)."""
    if sum(group_sizes) != len(meshes) or len(generators) != len(group_sizes):
        raise ValueError(f"{len(meshes)} meshes in groups {list(group_sizes)} with {len(generators)} generators")
    verts, faces = meshes.verts_packed(), meshes.faces_packed()
    if len(meshes) == 0:
        return verts.new_zeros(0, num_samples, 3)
    if faces.shape[0] == 0 or (meshes.shared_faces is None and bool((meshes.num_faces_per_mesh() == 0).any())):
        raise ValueError("sample_points_from_meshes: every mesh needs at least one face")
    with torch.no_grad():
        areas = _faces_padded(meshes, face_areas_packed(meshes))
        real = _faces_padded(meshes, torch.ones(faces.shape[0], dtype=verts.dtype, device=verts.device))
        degenerate = areas.sum(1, keepdim=True) <= 0
        weights = torch.where(degenerate, real, areas)
        local, r = [], []
        for group, generator in zip(weights.split(list(group_sizes)), generators, strict=True):
            if len(group):
                local.append(torch.multinomial(group, num_samples, replacement=True, generator=generator))
                shape = (len(group), num_samples, 2)
                r.append(torch.rand(shape, dtype=verts.dtype, device=verts.device, generator=generator))
        local, r = (torch.cat(parts) if len(parts) > 1 else parts[0] for parts in (local, r))
        first_face = torch.cumsum(meshes.num_faces_per_mesh(), 0) - meshes.num_faces_per_mesh()
        face_idx = local + first_face[:, None]
    corners = verts[faces[face_idx]]  # (B, S, 3 corners, 3)
    s = r[..., 0].sqrt()
    bary = torch.stack([1.0 - s, s * (1.0 - r[..., 1]), s * r[..., 1]], dim=-1)
    points = (bary.unsqueeze(-1) * corners).sum(-2)
    if not return_normals:
        return points
    v0, v1, v2 = corners.unbind(-2)
    normals = torch.nn.functional.normalize(torch.cross(v1 - v0, v2 - v0, dim=-1), dim=-1, eps=1e-12)
    return points, normals
