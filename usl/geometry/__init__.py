"""Geometry shared by every part of usl: cameras (docs/design.md §2), frustum homography, meshes."""

from usl.geometry.frustum import cube_to_frustum, frustum_homography, frustum_to_cube
from usl.geometry.icosphere import ico_sphere
from usl.geometry.meshes import Meshes
from usl.geometry.nearest import chamfer_directions, nearest_neighbors
from usl.geometry.sampling import face_areas_packed, sample_points_from_meshes, sample_points_in_groups
from usl.geometry.topology import MeshTemplate, faces_on_each_edge, uniform_laplacian, unique_edges

__all__ = [
    "MeshTemplate",
    "Meshes",
    "chamfer_directions",
    "cube_to_frustum",
    "face_areas_packed",
    "frustum_homography",
    "frustum_to_cube",
    "ico_sphere",
    "nearest_neighbors",
    "sample_points_from_meshes",
    "sample_points_in_groups",
    "faces_on_each_edge",
    "uniform_laplacian",
    "unique_edges",
]
