"""An analytic floor (the plane y = 0) composited behind the rendered objects.

Ray-casting the plane in numpy gives the floor's exact planar depth and a tiled albedo for a
fraction of what shading a floor polygon costs a software rasteriser (most pixels are floor).
The floor never occludes an object (objects stand on it), so compositing it behind the object
layer is exact. Shading follows pyrender's shader for a matte surface: Lambert diffuse with
albedo (1 - 0.04) / pi per directional light, plus ambient, then gamma 1/2.2.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

MAX_FLOOR_DEPTH = 15.0  # metres; beyond this the background colour shows (a horizon)
MIN_ROUGHNESS = 0.04  # pyrender's dielectric reflectance, removed from the diffuse albedo


@dataclass
class Light:
    direction: np.ndarray  # (3,) unit vector the light travels along, world frame
    radiance: np.ndarray  # (3,) colour * intensity


@dataclass
class FloorLook:
    albedo: np.ndarray  # (3,) linear RGB
    tile_size: float  # metres
    tile_contrast: float  # relative albedo difference of alternate tiles
    tile_angle: float  # radians, rotation of the tiling about +Y


def sample_floor(rng: np.random.Generator, albedo: np.ndarray) -> FloorLook:
    return FloorLook(
        np.asarray(albedo, dtype=np.float64), rng.uniform(0.25, 1.0), rng.uniform(0.0, 0.3), rng.uniform(0.0, np.pi / 2)
    )


class FloorRenderer:
    """The floor of one scene seen through one camera model (K, size) from any pose."""

    def __init__(
        self, look: FloorLook, lights: list[Light], ambient: np.ndarray, K: np.ndarray, height: int, width: int
    ):
        import torch  # not at import: the CLI's --help must not load torch

        from usl.geometry.cameras import unproject

        u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
        uv = torch.as_tensor(np.stack([u, v], axis=-1))
        # Camera-frame rays through pixel centres with z = 1: the ray parameter is planar depth.
        rays = unproject(uv, torch.ones(uv.shape[:-1], dtype=uv.dtype), torch.as_tensor(K, dtype=uv.dtype))
        self.rays = rays.numpy().astype(np.float32)
        self.look = look
        self.metres_per_pixel = 1.0 / float(np.sqrt(abs(np.linalg.det(K[:2, :2]))))  # at depth 1
        irradiance = ambient.astype(np.float64).copy()
        for light in lights:  # the floor's normal is +Y, the same for every pixel
            irradiance += (1.0 - MIN_ROUGHNESS) / np.pi * max(0.0, -float(light.direction[1])) * light.radiance
        self.base = (look.albedo * irradiance).astype(np.float32)

    def depth(self, cam_to_world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Planar depth of the floor at every pixel centre (0 where the ray misses it or it lies
        beyond MAX_FLOOR_DEPTH) and the world (x, z) of the hit points."""
        rotation = cam_to_world[:3, :3].astype(np.float32)
        eye = cam_to_world[:3, 3]
        down = self.rays @ rotation[1]  # world-y component of each ray
        with np.errstate(divide="ignore"):
            depth = np.where(down < 0, np.float32(-eye[1]) / down, np.float32(0.0))
        depth[depth > MAX_FLOOR_DEPTH] = 0.0
        points = eye[[0, 2]].astype(np.float32) + depth[..., None] * (self.rays @ rotation[[0, 2]].T)
        return depth, points

    def colour(self, depth: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Display-space RGB in [0, 1] of the floor at each pixel (meaningless where depth is 0)."""
        look = self.look
        c, s = (
            np.float32(np.cos(look.tile_angle) / look.tile_size),
            np.float32(np.sin(look.tile_angle) / look.tile_size),
        )
        x, z = points[..., 0], points[..., 1]
        checker = (np.floor(c * x - s * z) + np.floor(s * x + c * z)) % 2 - np.float32(0.5)
        # Fade the tiling where a pixel covers a sizeable part of a tile, instead of aliasing.
        footprint = depth * np.float32(self.metres_per_pixel / look.tile_size)
        pattern = 1.0 + np.float32(look.tile_contrast) * checker * np.clip(1.0 - 4.0 * footprint, 0.0, 1.0)
        return np.clip(pattern[..., None] * self.base, 0.0, 1.0) ** np.float32(1.0 / 2.2)
