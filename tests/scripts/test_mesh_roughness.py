"""scripts/mesh_roughness.py's figures against trimesh's face adjacency and a dense Laplacian."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch
import trimesh

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "scripts"))

import mesh_roughness  # noqa: E402
from usl.geometry import faces_on_each_edge, uniform_laplacian, unique_edges  # noqa: E402


def test_normal_consistency_and_laplacian_length_match_trimesh():
    rng = np.random.default_rng(0)
    sphere = trimesh.creation.icosphere(subdivisions=2)
    bumpy = sphere.copy()
    bumpy.vertices = bumpy.vertices * rng.uniform(0.7, 1.3, size=(len(bumpy.vertices), 1)) * [1.5, 0.6, 1.0]
    faces = torch.from_numpy(sphere.faces)
    pairs = faces_on_each_edge(faces)
    assert sorted(map(tuple, pairs.sort(dim=1).values.tolist())) == sorted(map(tuple, np.sort(sphere.face_adjacency, axis=1).tolist()))
    laplacian = uniform_laplacian(len(sphere.vertices), unique_edges(faces), torch.float64)
    verts = torch.from_numpy(np.stack([sphere.vertices, bumpy.vertices]))
    figures = mesh_roughness.roughness(verts, faces, pairs, laplacian)
    for mesh, (consistency, length) in zip((sphere, bumpy), figures.tolist()):
        assert np.isclose(consistency, np.mean(1.0 - np.cos(mesh.face_adjacency_angles)), atol=1e-9)
        centroids = np.stack([mesh.vertices[n].mean(0) for n in mesh.vertex_neighbors])
        assert np.isclose(length, np.linalg.norm(mesh.vertices - centroids, axis=1).mean(), atol=1e-9)
    assert figures[1, 0] > 10 * figures[0, 0]  # the bumps fold the faces; the sphere's are nearly flat
