"""Mesh connectivity helpers: unique edges, the faces on each edge and the uniform graph Laplacian."""

from __future__ import annotations

from dataclasses import dataclass

import torch

Tensor = torch.Tensor


def unique_edges(faces: Tensor, num_verts: int | None = None) -> Tensor:
    """Undirected edges of a triangle mesh, each once, as (E, 2) int64 with ``e[:, 0] < e[:, 1]``.

    Sorted lexicographically. ``faces`` (F, 3) may be a packed batch of meshes (edges
    never cross meshes then). ``num_verts`` defaults to ``faces.max() + 1``.
    """
    if faces.numel() == 0:
        return torch.zeros(0, 2, dtype=torch.int64, device=faces.device)
    faces = faces.long()
    n = int(faces.max()) + 1 if num_verts is None else int(num_verts)
    pairs = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    lo, hi = pairs.min(dim=1).values, pairs.max(dim=1).values
    keys = torch.unique(lo * n + hi)
    return torch.stack([keys // n, keys % n], dim=1)


def faces_on_each_edge(faces: Tensor) -> Tensor:
    """(E, 2): the two faces that share each edge of a closed triangle mesh, in ``unique_edges``' order."""
    sides = torch.cat([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).long().sort(dim=1).values
    _, edge = torch.unique(sides, dim=0, return_inverse=True)
    face = torch.arange(len(faces), device=faces.device).repeat(3)
    return face[edge.argsort(stable=True)].view(-1, 2)


@dataclass(frozen=True)
class MeshTemplate:
    """One triangle mesh's connectivity shared by many meshes (the model's ico-sphere per object).

    Its edges and the faces on them come from ``unique``, whose output size is read from the
    device: built once here, they are offset per mesh with no device read.
    """

    faces: Tensor  # (F, 3) int64
    edges: Tensor  # (E, 2): unique_edges(faces)
    edge_faces: Tensor  # (E, 2): faces_on_each_edge(faces)

    @classmethod
    def build(cls, faces: Tensor, num_verts: int) -> MeshTemplate:
        faces = faces.long()
        return cls(faces, unique_edges(faces, num_verts), faces_on_each_edge(faces))


def uniform_laplacian(num_verts: int, edges: Tensor, dtype: torch.dtype = torch.float32) -> Tensor:
    """Uniform (graph) Laplacian ``L = I - D^-1 A`` as a sparse COO (V, V) tensor.

    A is the symmetric adjacency of the undirected ``edges`` (E, 2) and D its degree
    matrix, so ``(L @ V)_i = v_i - mean of v_i's neighbours``: zero wherever a vertex is
    the centroid of its neighbours (e.g. interior vertices of a flat regular grid).
    This is PyTorch3D's uniform Laplacian up to its sign (PyTorch3D builds ``D^-1 A - I``),
    which no norm-based loss can tell apart. Isolated vertices get an all-zero row.
    """
    edges = edges.long()
    device = edges.device
    rows = torch.cat([edges[:, 0], edges[:, 1]])
    cols = torch.cat([edges[:, 1], edges[:, 0]])
    degree = torch.zeros(num_verts, dtype=dtype, device=device).index_add_(0, rows, torch.ones_like(rows, dtype=dtype))
    connected = torch.nonzero(degree > 0).squeeze(1)
    indices = torch.cat([torch.stack([rows, cols]), torch.stack([connected, connected])], dim=1)
    values = torch.cat([-1.0 / degree[rows], torch.ones_like(connected, dtype=dtype)])
    return torch.sparse_coo_tensor(indices, values, (num_verts, num_verts), check_invariants=True).coalesce()
