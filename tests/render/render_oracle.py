"""Independent oracle for the rasterizer tests: pyrender (OpenGL through EGL), driven by a
camera that takes the full 3x3 K, so tilt-shift intrinsics are checked too."""

from __future__ import annotations

import os

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np
import pyrender
import trimesh
from scipy.spatial.transform import Rotation

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])


class FullKCamera(pyrender.Camera):
    """A pyrender camera whose projection reproduces ``[u, v, 1] ~ K @ X_cam`` exactly.

    Clip rows in OpenCV camera coordinates: x = (2/W) k0 - k2, y = k2 - (2/H) k1 (pyrender
    flips rows on read-back, so NDC y = +1 is image row 0), w = k2, and z chosen as
    z = a w + b so that pyrender's depth linearisation returns the homogeneous depth w of
    K; for K with last row [0, 0, 1] that is the usual planar depth.
    """

    def __init__(self, K: np.ndarray, znear: float = 0.05, zfar: float = 50.0):
        super().__init__(znear=znear, zfar=zfar)
        self.K = np.asarray(K, dtype=np.float64)

    def get_projection_matrix(self, width=None, height=None):
        n, f = self.znear, self.zfar
        rows = np.zeros((4, 4))
        rows[:, :3] = np.stack(
            [
                2.0 / width * self.K[0] - self.K[2],
                self.K[2] - 2.0 / height * self.K[1],
                (f + n) / (f - n) * self.K[2],
                self.K[2],
            ]
        )
        rows[2, 3] = -2.0 * f * n / (f - n)
        return rows @ OPENCV_TO_OPENGL


def render_pyrender(
    meshes_world: list[trimesh.Trimesh], cam_to_world: np.ndarray, K: np.ndarray, height: int, width: int
):
    """Instance map (H, W) int (-1 background), planar depth (H, W) (0 background), and
    each mesh's unoccluded mask (M, H, W), as pyrender sees them."""
    scene = pyrender.Scene(bg_color=[0, 0, 0, 0])
    material = pyrender.MetallicRoughnessMaterial(doubleSided=True)
    nodes = [scene.add(pyrender.Mesh.from_trimesh(m, material=material, smooth=False)) for m in meshes_world]
    scene.add(FullKCamera(K), pose=cam_to_world @ OPENCV_TO_OPENGL)
    colours = {node: _colour(i) for i, node in enumerate(nodes)}
    renderer = pyrender.OffscreenRenderer(width, height)
    try:
        seg, w_depth = renderer.render(scene, flags=pyrender.RenderFlags.SEG, seg_node_map=colours)
        alone = [
            renderer.render(scene, flags=pyrender.RenderFlags.SEG, seg_node_map={node: colours[node]})[0]
            for node in nodes
        ]
    finally:
        renderer.delete()
    instance = _decode(seg, len(nodes))
    masks = np.stack([_decode(img, len(nodes)) == i for i, img in enumerate(alone)])
    return instance, _planar_depth(w_depth, K), masks


def _colour(index: int) -> np.ndarray:
    code = index + 1
    return np.array([code % 256, (code // 256) % 256, 255], dtype=np.uint8)


def _decode(seg: np.ndarray, count: int) -> np.ndarray:
    code = seg[..., 0].astype(np.int64) + 256 * seg[..., 1].astype(np.int64)
    instance = np.where(seg[..., 2] == 255, code - 1, -1)
    assert instance.max() < count
    return instance


def _planar_depth(w_depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Homogeneous depth w per pixel -> planar z: X = w K^-1 [u, v, 1] at pixel centres."""
    height, width = w_depth.shape
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ np.linalg.inv(K).T
    return w_depth * rays[..., 2]


def random_scene(rng: np.random.Generator, count: int) -> list[trimesh.Trimesh]:
    """Convex and non-convex meshes at random poses, 1.5-4 m in front of an OpenCV camera
    at the origin (so the coordinates are camera-frame)."""
    makers = [
        lambda: trimesh.creation.icosphere(subdivisions=2, radius=rng.uniform(0.2, 0.45)),
        lambda: trimesh.creation.box(extents=rng.uniform(0.15, 0.7, size=3)),
        lambda: trimesh.creation.capsule(height=rng.uniform(0.2, 0.6), radius=rng.uniform(0.08, 0.2)),
        lambda: trimesh.creation.annulus(r_min=0.12, r_max=0.35, height=rng.uniform(0.05, 0.3)),
        lambda: trimesh.convex.convex_hull(rng.normal(size=(30, 3)) * 0.25),
    ]
    meshes = []
    for i in range(count):
        mesh = makers[i % len(makers)]()
        pose = np.eye(4)
        pose[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
        pose[:3, 3] = [rng.uniform(-0.7, 0.7), rng.uniform(-0.5, 0.5), rng.uniform(1.5, 4.0)]
        meshes.append(mesh.apply_transform(pose))
    return meshes


def random_rigid(rng: np.random.Generator) -> np.ndarray:
    """A random 4x4 cam_to_world."""
    pose = np.eye(4)
    pose[:3, :3] = Rotation.random(random_state=rng.integers(1 << 31)).as_matrix()
    pose[:3, 3] = rng.uniform(-3.0, 3.0, size=3)
    return pose


def intrinsics(height: int, width: int, tilt: tuple[float, float] = (0.0, 0.0)) -> np.ndarray:
    """A K for the image size; ``tilt`` fills the last row [a, b, 1] (tilt-shift)."""
    f = 1.1 * max(height, width)
    return np.array([[f, 0.0, 0.52 * width], [0.0, 1.05 * f, 0.47 * height], [tilt[0], tilt[1], 1.0]])
