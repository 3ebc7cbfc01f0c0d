"""Geometrically exact multi-view records for the training tests: cuboids seen by an orbiting camera.

Like Scene-Shapes (docs/design.md §4) at toy size: two yawed cuboids on the Y = 0 floor at
X in [-0.4, 0.4], Z in [1.5, 1.9] of the first camera's ground frame (Y up), and a camera
orbiting the vertical axis through (0, 0, 1.7) at radius 1.7, looking at (0, 0.3, 1.7).
Masks come from ``usl.render.rasterize_hard`` (a z-buffer checked against pyrender by the
render tests), so every view's silhouettes, ids and poses agree exactly. Pixels are each
object's colour shaded by depth, on a plain background.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from pipelines.common import BuildOptions, ShardPlan, run_build
from usl.geometry.cameras import intrinsics_from_fov
from usl.records import SceneRecord, encode_depth, encode_image, frame_row, make_instance, object_row
from usl.render import rasterize_hard

SPEC = {
    "name": "synthetic_cuboids",
    "categories": [{"id": 3, "name": "crate"}, {"id": 5, "name": "slab"}],
    # Wide on purpose: a fresh layout head predicts mid-range (z = 3.25 m), far from the true
    # ~1.7 m, so learning the layout shows in every metric.
    "layout": {"z0": 0.5, "z1": 6.0, "rho0": 0.1, "rho1": 2.0},
}
ORBIT_Z = 1.7
TARGET_HEIGHT = 0.3
FOV = math.radians(60.0)

_CUBE = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64) / 2
_CUBE_FACES = np.array(
    [[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
     [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]],
    dtype=np.int64,
)


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """cam_to_world (4x4) of an OpenCV camera (x right, y down, z forward) in a Y-up world."""
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, [0.0, 1.0, 0.0])
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, down, forward], axis=1)
    pose[:3, 3] = eye
    return pose


def cuboid(rng: np.random.Generator, category: int) -> tuple[np.ndarray, np.ndarray]:
    """World-frame vertices and faces of a yawed cuboid standing on the floor."""
    size = rng.uniform([0.4, 0.3, 0.3], [0.7, 0.6, 0.6]) if category == 3 else rng.uniform([0.6, 0.15, 0.3], [0.9, 0.3, 0.5])
    yaw = rng.uniform(0, 2 * math.pi)
    rot = np.array([[math.cos(yaw), 0, math.sin(yaw)], [0, 1, 0], [-math.sin(yaw), 0, math.cos(yaw)]])
    centre = np.array([rng.uniform(-0.4, 0.4), size[1] / 2, rng.uniform(1.5, 1.9)])
    return (_CUBE * size) @ rot.T + centre, _CUBE_FACES


def build_scene(unit: tuple[str, int, int, int]) -> SceneRecord:
    """``unit = (scene_id, seed, num_views, image_size)``."""
    scene_id, seed, num_views, size = unit
    rng = np.random.default_rng(seed)
    categories = [3, 5]
    meshes = [cuboid(rng, c) for c in categories]
    colours = rng.uniform(0.3, 1.0, (len(meshes), 3))
    background = rng.uniform(0.0, 0.25, 3)
    K = intrinsics_from_fov(FOV, size, size)
    frames = []
    for view in range(num_views):
        angle = 2 * math.pi * view / num_views
        height = 0.6 if view % 2 == 0 else 1.2
        eye = np.array([ORBIT_Z * math.sin(angle), height, ORBIT_Z - ORBIT_Z * math.cos(angle)])
        pose = look_at(eye, np.array([0.0, TARGET_HEIGHT, ORBIT_Z]))
        world_to_cam = np.linalg.inv(pose)
        verts = [v @ world_to_cam[:3, :3].T + world_to_cam[:3, 3] for v, _ in meshes]
        offsets = np.cumsum([0] + [len(v) for v in verts])[:-1]
        render = rasterize_hard(
            torch.from_numpy(np.concatenate(verts)),
            torch.from_numpy(np.concatenate([f + o for (_, f), o in zip(meshes, offsets)])),
            torch.arange(len(meshes)).repeat_interleave(len(_CUBE_FACES)),
            K,
            size,
            size,
        )
        depth = render.depth_map.numpy()
        shade = np.clip(1.3 - 0.3 * np.nan_to_num(depth, posinf=0.0), 0.2, 1.0)[..., None]
        image = np.broadcast_to(background, (size, size, 3)).copy()
        instances = []
        for index, mask in enumerate(render.masks.numpy()):
            image[mask] = (colours[index] * shade)[mask]
            if mask.any():
                instances.append(make_instance(index + 1, categories[index], mask, np.where(np.isinf(depth), np.nan, depth)))
        frames.append(
            frame_row(scene_id, view, encode_image((image * 255).astype(np.uint8)), K.numpy(), pose, instances,
                      size, size, encode_depth(np.where(np.isinf(depth), 0.0, depth)))
        )
    objects = [
        object_row(scene_id, index + 1, c, f"cuboid-{seed}-{index}", v.astype(np.float32), f)
        for index, ((v, f), c) in enumerate(zip(meshes, categories))
    ]
    return SceneRecord(scene_id, frames, objects)


def build_synthetic_records(
    root: Path, num_scenes: int = 4, num_views: int = 6, size: int = 64, val_scenes: int = 1, seed: int = 0
) -> Path:
    """Write a records folder with ``num_scenes`` train and ``val_scenes`` val scenes."""
    units = [(f"scene{k:03d}", seed * 1000 + k, num_views, size) for k in range(num_scenes + val_scenes)]
    plans = [ShardPlan("train", 0, units[:num_scenes])]
    if val_scenes:
        plans.append(ShardPlan("val", 0, units[num_scenes:]))
    run_build(BuildOptions(Path(root), progress=False), SPEC, {"seed": seed, "size": size}, plans, build_scene,
              {"command": "tests/data/synthetic_records.py"})
    return Path(root)
