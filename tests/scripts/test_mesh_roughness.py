"""scripts/experiments/mesh_roughness.py's figures: normal consistency (tested in tests/losses) and the Laplacian's
length against trimesh."""

from __future__ import annotations

import mesh_roughness
import numpy as np
import torch
import trimesh

from usl.geometry import faces_on_each_edge, uniform_laplacian, unique_edges


def test_roughness_is_normal_consistency_and_the_mean_distance_to_the_neighbours_centroid():
    mesh = trimesh.creation.icosphere(subdivisions=1)
    mesh.vertices = mesh.vertices + np.random.default_rng(1).normal(0.0, 0.1, mesh.vertices.shape)
    faces = torch.from_numpy(mesh.faces)
    verts = torch.from_numpy(mesh.vertices)[None]
    laplacian = uniform_laplacian(len(mesh.vertices), unique_edges(faces), torch.float64)
    consistency, length = mesh_roughness.roughness(verts, faces, faces_on_each_edge(faces), laplacian)[0].tolist()
    assert np.isclose(consistency, np.mean(1.0 - np.cos(mesh.face_adjacency_angles)), atol=1e-9)
    centroids = np.stack([mesh.vertices[n].mean(0) for n in mesh.vertex_neighbors])
    assert np.isclose(length, np.linalg.norm(mesh.vertices - centroids, axis=1).mean(), atol=1e-9)
