"""Independent oracles for built Scene-Shapes records: re-render one stored mesh alone with pyrender
from the stored K and pose, back-project stored depth with numpy, and measure distances to a mesh
with trimesh's exact point-triangle routine (no builder code involved)."""

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np
import pyrender
import trimesh

_RENDERERS = {}
GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # OpenCV camera axes -> OpenGL camera axes


def render_depth_alone(vertices, faces, K, cam_to_world, height, width):
    """Planar depth of one mesh alone (0 where it is absent).

    Uses the SEG pass because it rasterises without multisampling: coverage and depth are taken at
    pixel centres, as the records promise (a multisampled depth resolve would pick an off-centre sample).
    """
    key = (width, height)
    if key not in _RENDERERS:
        _RENDERERS[key] = pyrender.OffscreenRenderer(width, height)
    scene = pyrender.Scene()
    node = scene.add(pyrender.Mesh.from_trimesh(trimesh.Trimesh(vertices, faces, process=False)))
    scene.add(
        pyrender.IntrinsicsCamera(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], znear=0.01, zfar=100.0),
        pose=cam_to_world @ GL_FROM_CV,
    )
    _, depth = _RENDERERS[key].render(scene, flags=pyrender.RenderFlags.SEG, seg_node_map={node: [255, 255, 255]})
    return depth


def backproject(depth, K, cam_to_world, rows, cols):
    """World points of pixel centres (rows, cols) with planar depth: X_cam = d K^-1 [u, v, 1]."""
    uv1 = np.stack([cols + 0.5, rows + 0.5, np.ones(len(rows))], axis=1)
    rays = uv1 @ np.linalg.inv(K).T
    cam = rays / rays[:, 2:3] * depth[rows, cols][:, None]
    return cam @ cam_to_world[:3, :3].T + cam_to_world[:3, 3]


def distance_to_mesh(points, vertices, faces):
    """Exact distance of each point to the mesh surface (brute force over all triangles)."""
    triangles = vertices[faces]
    best = np.full(len(points), np.inf)
    for start in range(0, len(points), 64):
        chunk = points[start : start + 64]
        pairs = np.repeat(chunk, len(triangles), axis=0)
        closest = trimesh.triangles.closest_point(np.tile(triangles, (len(chunk), 1, 1)), pairs)
        best[start : start + 64] = np.linalg.norm(closest - pairs, axis=1).reshape(len(chunk), -1).min(axis=1)
    return best


def iou(a, b):
    union = np.logical_or(a, b).sum()
    return np.logical_and(a, b).sum() / union if union else 1.0
