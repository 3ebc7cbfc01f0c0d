"""Scene layout as in the paper (Appendix B): an object pair on the floor and an orbiting camera.

World frame (what ``cam_to_world`` and the stored meshes use): the *first camera's ground frame*.
Origin on the floor directly below camera 0, +Y up, +Z camera 0's horizontal viewing direction,
+X = +Y x +Z (camera 0's left; right-handed), metres. Each object is yawed uniformly in
[0, 2 pi) about +Y and its bounding-box centre put at (X, 0, Z) with X in [-0.4, 0.4] and
Z in [1.5, 1.9], i.e. relative to the first camera, as the paper states (``PlacementConfig``).

Cameras orbit the vertical axis through (0, 0, Zc), Zc the middle of the Z range, at radius Zc,
so camera 0 (azimuth 0) sits on that orbit at the origin. Each camera looks at (0, h_t, Zc) with
h_t = ``target_height``. Views are a grid of ``heights`` camera heights x ``azimuths`` azimuths,
``view_id = height_index * azimuths + azimuth_index`` (heights ascending, so view 0 is camera 0 at
the lowest height); azimuths are evenly spaced with a small per-scene random jitter (never on
azimuth 0, which defines the world frame).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .shapes import ModelRef


@dataclass(frozen=True)
class RigConfig:
    """Camera orbit and intrinsics."""

    azimuths: int = 8
    heights: int = 3
    height_range: tuple[float, float] = (0.8, 1.8)  # camera heights above the floor, metres
    target_height: float = 0.4  # height of the orbit centre the cameras look at
    fov_deg: float = 70.0  # horizontal = vertical field of view of the square images
    resolution: int = 512
    azimuth_jitter: float = 0.25  # max jitter, as a fraction of the azimuth step

    @property
    def num_views(self) -> int:
        return self.azimuths * self.heights

    def camera_heights(self) -> np.ndarray:
        if self.heights == 1:
            return np.array([0.5 * sum(self.height_range)])
        return np.linspace(self.height_range[0], self.height_range[1], self.heights)


@dataclass(frozen=True)
class PlacementConfig:
    """Where objects go, in the first camera's ground frame (paper: X in [-0.4, 0.4], Z in [1.5, 1.9])."""

    objects_per_scene: int = 2
    x_range: tuple[float, float] = (-0.4, 0.4)
    z_range: tuple[float, float] = (1.5, 1.9)

    @property
    def orbit_center_z(self) -> float:
        return 0.5 * (self.z_range[0] + self.z_range[1])


@dataclass(frozen=True)
class ObjectPlacement:
    instance_id: int
    model: ModelRef
    yaw: float
    x: float
    z: float

    def world_from_object(self) -> np.ndarray:
        """4x4 transform of the grounded model into the world: yaw about +Y, then move to (x, 0, z)."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, 0.0, s, self.x], [0.0, 1.0, 0.0, 0.0], [-s, 0.0, c, self.z], [0.0, 0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class SceneLayout:
    objects: tuple[ObjectPlacement, ...]
    cam_to_world: tuple[np.ndarray, ...]  # per view, OpenCV camera -> world, 4x4
    K: np.ndarray  # 3x3, shared by all views


def orbit_poses(rig: RigConfig, placement: PlacementConfig, rng: np.random.Generator) -> list[np.ndarray]:
    """Camera poses of all views, in view_id order; view 0 sits at the world origin's vertical."""
    from usl.geometry.cameras import look_at  # torch: not at import (fast --help)

    radius = placement.orbit_center_z
    target = np.array([0.0, rig.target_height, radius])
    step = 2 * math.pi / rig.azimuths
    jitter = rng.uniform(-rig.azimuth_jitter, rig.azimuth_jitter, size=rig.azimuths) * step
    jitter[0] = 0.0
    poses = []
    for height in rig.camera_heights():
        for a in range(rig.azimuths):
            phi = a * step + jitter[a]
            eye = np.array([radius * math.sin(phi), height, radius * (1.0 - math.cos(phi))])
            poses.append(look_at(eye, target))
    return poses


def sample_layout(
    rng: np.random.Generator, pools: dict[str, list[ModelRef]], rig: RigConfig, placement: PlacementConfig
) -> SceneLayout:
    """Pick the objects (a uniformly chosen category each, then a model of it), their yaws and
    positions, and the camera orbit of one scene.

    A scene never holds the same model twice unless the split has no other model at all: two
    copies of one model can have coincident surfaces (equal table tops), whose pixels would belong
    to either object at random (z-fighting).
    """
    objects: list[ObjectPlacement] = []
    used: set[str] = set()
    for instance_id in range(1, placement.objects_per_scene + 1):
        fresh = {c: [r for r in refs if r.source_id not in used] for c, refs in sorted(pools.items())}
        candidates = {c: refs for c, refs in fresh.items() if refs} or {c: refs for c, refs in pools.items() if refs}
        categories = sorted(candidates)
        pool = candidates[categories[int(rng.integers(len(categories)))]]
        model = pool[int(rng.integers(len(pool)))]
        used.add(model.source_id)
        yaw = float(rng.uniform(0.0, 2 * math.pi))
        x = float(rng.uniform(*placement.x_range))
        z = float(rng.uniform(*placement.z_range))
        objects.append(ObjectPlacement(instance_id, model, yaw, x, z))
    from usl.geometry.cameras import intrinsics_from_fov

    K = intrinsics_from_fov(math.radians(rig.fov_deg), rig.resolution, rig.resolution).numpy()
    return SceneLayout(tuple(objects), tuple(orbit_poses(rig, placement, rng)), K)
