"""Offscreen rendering of one scene from all its views with pyrender (EGL).

Per view two passes: a lit RGBA pass of the objects (multisampled, random materials and
lights, transparent background) and a flat segmentation pass without multisampling, whose
colours are instance indices and whose depth is exact at pixel centres. Masks and object depth
both come from the segmentation pass, so a pixel belongs to the nearest object and masks and
depth always agree. The background (a plain colour, optionally with the analytic floor of
``floor.py``) is composited behind the anti-aliased object layer.
"""

from __future__ import annotations

import colorsys
import importlib.util
import os
from dataclasses import dataclass
from typing import TYPE_CHECKING

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")  # must precede the first OpenGL import
# Mesa's software rasteriser (llvmpipe) measured ~2x faster per frame with one thread than with
# two on 2 cores; builds parallelise over worker processes instead. GPUs ignore this variable.
os.environ.setdefault("LP_NUM_THREADS", "1")

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from usl.errors import UslError  # noqa: E402

from .floor import FloorRenderer, Light, sample_floor  # noqa: E402
from .primitives import BODY, FRAME  # noqa: E402
from .shapes import ShapeModel  # noqa: E402

if TYPE_CHECKING:
    import pyrender

Z_NEAR, Z_FAR = 0.05, 30.0
BACKGROUNDS = ("plain", "floor")
_RENDERERS: dict[tuple[int, int], pyrender.OffscreenRenderer] = {}

EGL_HELP = (
    "offscreen rendering failed ({error}); install libegl1 and libgl1-mesa-dri "
    "(Debian/Ubuntu) and set PYOPENGL_PLATFORM=egl"
)


def _egl_error(exc: BaseException) -> UslError:
    return UslError(EGL_HELP.format(error=f"{type(exc).__name__}: {exc}".strip()))


def load_triton_before_mesa() -> None:
    """Load triton now if it is installed, before an EGL context exists. Mesa's software EGL
    (llvmpipe) loads the system's libLLVM; a CUDA build of torch ships triton with an LLVM of its
    own, and loading triton after Mesa's LLVM crashes the process (a segmentation fault in the
    dynamic loader). torch imports triton lazily (``torch.compile``, ``torch._dynamo``, the fused
    optimizers), so one process that renders with pyrender and later trains would crash at its
    first optimizer step. In the other order both work. Costs about 0.1 s where triton exists."""
    if importlib.util.find_spec("triton") is not None:
        import triton  # noqa: F401


def _pyrender():
    """pyrender, imported on first use: without a usable libEGL/libGL its import already fails,
    and that must become the one-line hint rather than a traceback at CLI start-up."""
    load_triton_before_mesa()
    try:
        import pyrender
    except Exception as exc:  # ImportError, or OpenGL platform errors of several types
        raise _egl_error(exc) from exc
    return pyrender


@dataclass
class ViewImages:
    rgb: np.ndarray  # (H, W, 3) uint8
    depth: np.ndarray  # (H, W) float32 planar depth in metres, 0 where nothing was hit
    instance_index: np.ndarray  # (H, W) uint8: 0 background/floor, k = objects[k - 1]


@dataclass
class PlacedModel:
    model: ShapeModel
    world_from_object: np.ndarray  # 4x4


def renderer_for(width: int, height: int) -> pyrender.OffscreenRenderer:
    """One renderer per process and size (creating an EGL context per scene would dominate)."""
    key = (width, height)
    if key not in _RENDERERS:
        pyrender = _pyrender()
        try:
            _RENDERERS[key] = pyrender.OffscreenRenderer(width, height)
        except Exception as exc:  # EGL/OpenGL failures come as many exception types
            raise _egl_error(exc) from exc
    return _RENDERERS[key]


def check_offscreen_rendering(resolution: int) -> None:
    """Fail early, with the one-line hint, when this machine cannot render offscreen.

    The renderer stays cached for this process: deleting a pyrender EGL renderer terminates the
    process-wide EGL display and with it every other renderer's context.
    """
    renderer_for(resolution, resolution)


def _random_color(rng: np.random.Generator, value: tuple[float, float]) -> np.ndarray:
    return np.array(colorsys.hsv_to_rgb(rng.uniform(), rng.uniform(0.05, 0.8), rng.uniform(*value)))


def _material(rng: np.random.Generator, role: int) -> pyrender.MetallicRoughnessMaterial:
    """Upholstery/tops: matte to satin; frames: wood-like or metallic."""
    pyrender = _pyrender()
    metallic = rng.uniform(0.0, 0.1) if role == BODY else rng.choice([rng.uniform(0.0, 0.1), rng.uniform(0.6, 0.9)])
    return pyrender.MetallicRoughnessMaterial(
        baseColorFactor=[*_random_color(rng, (0.15, 0.95)), 1.0],
        metallicFactor=float(metallic),
        roughnessFactor=float(rng.uniform(0.3, 1.0)),
    )


def _object_mesh(model: ShapeModel, rng: np.random.Generator) -> pyrender.Mesh:
    """A pyrender mesh with one primitive per part role, smooth-shaded except across sharp edges."""
    pyrender = _pyrender()
    primitives = []
    for role in (BODY, FRAME):
        faces = model.faces[model.vertex_roles[model.faces[:, 0]] == role]
        if len(faces) == 0:
            continue
        mesh = trimesh.Trimesh(model.vertices, faces, process=False).smooth_shaded
        primitives += pyrender.Mesh.from_trimesh(mesh, material=_material(rng, role), smooth=True).primitives
    return pyrender.Mesh(primitives=primitives)


def _sample_lights(rng: np.random.Generator) -> list[Light]:
    """A key and a fill directional light from random directions above the floor, slightly tinted."""
    lights = []
    for intensity in (rng.uniform(2.0, 5.0), rng.uniform(0.3, 1.5)):
        elevation, azimuth = rng.uniform(np.radians(25), np.radians(85)), rng.uniform(0, 2 * np.pi)
        direction = -np.array(
            [np.cos(elevation) * np.sin(azimuth), np.sin(elevation), np.cos(elevation) * np.cos(azimuth)]
        )
        lights.append(Light(direction, intensity * (1.0 - rng.uniform(0.0, 0.15, size=3))))
    return lights


def _light_node_pose(direction: np.ndarray) -> np.ndarray:
    """Pose of a pyrender directional light (it shines along its node's -z) travelling along ``direction``."""
    pose = np.eye(4)
    pose[:3, 2] = -direction
    pose[:3, 0] = np.cross([0.0, 1.0, 0.0], pose[:3, 2])
    pose[:3, 0] /= np.linalg.norm(pose[:3, 0])
    pose[:3, 1] = np.cross(pose[:3, 2], pose[:3, 0])
    return pose


def render_scene(
    objects: list[PlacedModel],
    K: np.ndarray,
    cam_to_world: list[np.ndarray],
    resolution: int,
    background: str,
    rng: np.random.Generator,
) -> list[ViewImages]:
    """Render every view of a scene; ``rng`` drives materials, lights and background only."""
    if K[0, 1] != 0.0 or K[1, 0] != 0.0 or np.any(K[2] != [0.0, 0.0, 1.0]):
        raise ValueError("pyrender cameras need a K without skew and a last row [0, 0, 1]")
    renderer = renderer_for(resolution, resolution)
    pyrender = _pyrender()
    from OpenGL.error import Error as GLError  # importable once pyrender is

    ambient = np.full(3, rng.uniform(0.1, 0.4))
    scene = pyrender.Scene(bg_color=[0.0, 0.0, 0.0, 0.0], ambient_light=ambient)
    seg_map = {}
    for k, placed in enumerate(objects, start=1):
        seg_map[scene.add(_object_mesh(placed.model, rng), pose=placed.world_from_object)] = [k, 0, 0]
    lights = _sample_lights(rng)
    for light in lights:
        scene.add(
            pyrender.DirectionalLight(
                color=light.radiance / light.radiance.max(), intensity=float(light.radiance.max())
            ),
            pose=_light_node_pose(light.direction),
        )
    sky = (_random_color(rng, (0.2, 1.0)) ** (1.0 / 2.2)).astype(np.float32)
    floor = None
    if background == "floor":
        look = sample_floor(rng, _random_color(rng, (0.2, 0.9)))
        floor = FloorRenderer(look, lights, ambient, K, resolution, resolution)
    camera_node = scene.add(
        pyrender.IntrinsicsCamera(fx=K[0, 0], fy=K[1, 1], cx=K[0, 2], cy=K[1, 2], znear=Z_NEAR, zfar=Z_FAR)
    )
    from usl.geometry.cameras import opencv_to_opengl_camera  # torch: not at import (fast --help)

    opencv_to_opengl = opencv_to_opengl_camera().numpy()
    views = []
    try:
        for pose in cam_to_world:
            scene.set_pose(camera_node, pose @ opencv_to_opengl)
            rgba, _ = renderer.render(scene, flags=pyrender.RenderFlags.RGBA)
            seg, depth = renderer.render(scene, flags=pyrender.RenderFlags.SEG, seg_node_map=seg_map)
            back = np.broadcast_to(sky, (resolution, resolution, 3))
            if floor is not None:
                ground, points = floor.depth(pose)
                back = np.where(ground[..., None] > 0, floor.colour(ground, points), back)
                depth = np.where(depth > 0, depth, ground)
            # The object layer is premultiplied by its coverage (transparent background, MSAA resolve).
            alpha = rgba[..., 3:4].astype(np.float32) * np.float32(1.0 / 255.0)
            rgb = rgba[..., :3] + (1.0 - alpha) * np.float32(255.0) * back + np.float32(0.5)
            views.append(
                ViewImages(np.clip(rgb, 0, 255).astype(np.uint8), depth.astype(np.float32), seg[..., 0].copy())
            )
    except GLError as exc:
        raise _egl_error(exc) from exc
    return views
