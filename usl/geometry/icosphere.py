"""Ico-spheres: the identical initial mesh the shape head deforms for every object (paper Sec. 3.3)."""

from __future__ import annotations

import functools
import math

import torch

from usl.geometry.topology import unique_edges

Tensor = torch.Tensor


def _icosahedron() -> tuple[Tensor, Tensor]:
    """The 12 vertices (on the unit sphere) and 20 faces of a regular icosahedron, float64."""
    t = (1.0 + math.sqrt(5.0)) / 2.0
    verts = torch.tensor(
        [
            [-1, t, 0],
            [1, t, 0],
            [-1, -t, 0],
            [1, -t, 0],
            [0, -1, t],
            [0, 1, t],
            [0, -1, -t],
            [0, 1, -t],
            [t, 0, -1],
            [t, 0, 1],
            [-t, 0, -1],
            [-t, 0, 1],
        ],
        dtype=torch.float64,
    )
    faces = torch.tensor(
        [
            [0, 11, 5],
            [0, 5, 1],
            [0, 1, 7],
            [0, 7, 10],
            [0, 10, 11],
            [1, 5, 9],
            [5, 11, 4],
            [11, 10, 2],
            [10, 7, 6],
            [7, 1, 8],
            [3, 9, 4],
            [3, 4, 2],
            [3, 2, 6],
            [3, 6, 8],
            [3, 8, 9],
            [4, 9, 5],
            [2, 4, 11],
            [6, 2, 10],
            [8, 6, 7],
            [9, 8, 1],
        ],
        dtype=torch.int64,
    )
    return verts / verts.norm(dim=1, keepdim=True), faces


def _orient_outward(verts: Tensor, faces: Tensor) -> Tensor:
    """Reorder each face's corners so its normal points away from the origin (CCW from outside)."""
    v0, v1, v2 = verts[faces].unbind(1)
    outward = (torch.cross(v1 - v0, v2 - v0, dim=1) * (v0 + v1 + v2)).sum(1) > 0
    return torch.where(outward[:, None], faces, faces[:, [0, 2, 1]])


def _subdivide(verts: Tensor, faces: Tensor) -> tuple[Tensor, Tensor]:
    """Loop-style 1-to-4 split: one new vertex per edge midpoint, projected onto the sphere.

    The corner order of every child face follows its parent, so the winding is kept.
    """
    edges = unique_edges(faces)
    num_verts = verts.shape[0]
    midpoints = 0.5 * (verts[edges[:, 0]] + verts[edges[:, 1]])
    new_verts = torch.cat([verts, midpoints / midpoints.norm(dim=1, keepdim=True)])
    # Look up the midpoint index of each face edge through the sorted edge keys.
    keys = edges[:, 0] * num_verts + edges[:, 1]

    def midpoint_index(a: Tensor, b: Tensor) -> Tensor:
        key = torch.minimum(a, b) * num_verts + torch.maximum(a, b)
        return num_verts + torch.searchsorted(keys, key)

    a, b, c = faces.unbind(1)
    ab, bc, ca = midpoint_index(a, b), midpoint_index(b, c), midpoint_index(c, a)
    new_faces = torch.cat([torch.stack(f, dim=1) for f in ((a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca))])
    return new_verts, new_faces


@functools.lru_cache(maxsize=8)
def _ico_sphere_cpu(level: int) -> tuple[Tensor, Tensor]:
    verts, faces = _icosahedron()
    faces = _orient_outward(verts, faces)
    for _ in range(level):
        verts, faces = _subdivide(verts, faces)
    return verts, faces


def ico_sphere(
    level: int, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
) -> tuple[Tensor, Tensor]:
    """Unit ico-sphere of subdivision ``level``.

    Returns:
        verts: (10 * 4**level + 2, 3) points on the unit sphere.
        faces: (20 * 4**level, 3) int64, counter-clockwise seen from outside (outward normals).
    Built in float64 once per level (cached) and returned as fresh copies.
    """
    if level < 0:
        raise ValueError(f"ico_sphere level must be >= 0, got {level}")
    verts, faces = _ico_sphere_cpu(int(level))
    return verts.to(dtype=dtype, device=device, copy=True), faces.to(device=device, copy=True)
