"""A rendered capture with known truth, for tests and ``scripts/bench/captures_sfm.py``.

A room (floor and walls) with a table and a chair, every surface covered in multi-scale random
noise so that SIFT finds features, seen by a camera moving along an arc. pyrender gives per frame
the image, the planar depth and each object's visible mask. Writers put it on disk in the formats
``usl-convert-captures`` reads: ``transforms.json`` (OpenGL axes, 16-bit millimetre depth), a COLMAP
model (text, world scaled to an arbitrary unit, sparse points sampled from the depth), and
``detections.json`` (COCO results in random order, plus decoys the converter must drop).
"""

from __future__ import annotations

import ctypes
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import trimesh
from pycocotools import mask as mask_utils
from scipy.spatial.transform import Rotation

from pipelines.captures.posed import OPENGL_TO_OPENCV
from pipelines.scene_shapes.render import renderer_for

CHAIR_COCO, TABLE_COCO, PERSON_COCO = 62, 67, 1
# (name, COCO id, boxes as (centre xyz, size xyz) in metres, world y up)
OBJECTS = (
    (
        "table",
        TABLE_COCO,
        [((0.0, 0.74, 0.0), (1.2, 0.05, 0.8))]
        + [((x, 0.36, z), (0.06, 0.72, 0.06)) for x in (-0.55, 0.55) for z in (-0.35, 0.35)],
    ),
    (
        "chair",
        CHAIR_COCO,
        [((0.95, 0.45, 0.55), (0.45, 0.05, 0.45)), ((0.95, 0.72, 0.76), (0.45, 0.5, 0.05))]
        + [((0.95 + x, 0.21, 0.55 + z), (0.04, 0.42, 0.04)) for x in (-0.2, 0.2) for z in (-0.2, 0.2)],
    ),
)
ROOM = (
    ((0.0, -0.05, 0.0), (7.0, 0.1, 7.0)),
    ((0.0, 1.4, -3.5), (7.0, 2.8, 0.1)),
    ((-3.5, 1.4, 0.0), (0.1, 2.8, 7.0)),
    ((3.5, 1.4, 0.0), (0.1, 2.8, 7.0)),
    ((0.0, 1.4, 3.5), (7.0, 2.8, 0.1)),
)


def noise_texture(rng: np.random.Generator, size: int = 1024, blobs: int = 600) -> np.ndarray:
    """Smooth colour noise under sharp random discs of many sizes: blobs and corners for SIFT at any distance."""
    image = np.zeros((size, size, 3), np.float32)
    for cells in (4, 16, 64):
        image += cv2.resize(rng.random((cells, cells, 3), np.float32), (size, size), interpolation=cv2.INTER_CUBIC)
    low, high = np.percentile(image, (2, 98))
    image = (255 * np.clip((image - low) / (high - low), 0, 1)).astype(np.uint8)
    for _ in range(blobs):
        centre = (int(rng.integers(size)), int(rng.integers(size)))
        radius = int(size * rng.uniform(0.004, 0.04))
        cv2.circle(image, centre, radius, [int(v) for v in rng.integers(0, 256, 3)], -1, cv2.LINE_AA)
    return image


def textured_box(centre, size, texture: np.ndarray) -> trimesh.Trimesh:
    """A box whose six faces each carry the whole texture (UVs per face corner)."""
    from PIL import Image

    half = np.asarray(size, float) / 2
    vertices, faces, uv = [], [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            u_axis, v_axis = [a for a in range(3) if a != axis]
            corners = []
            for du, dv in ((-1, -1), (1, -1), (1, 1), (-1, 1)):
                p = np.zeros(3)
                p[axis], p[u_axis], p[v_axis] = sign * half[axis], du * half[u_axis], dv * half[v_axis]
                corners.append(p + centre)
            base = len(vertices)
            vertices += corners
            uv += [(0, 0), (1, 0), (1, 1), (0, 1)]
            faces += [
                (base, base + 1, base + 2),
                (base, base + 2, base + 3),
                (base, base + 2, base + 1),
                (base, base + 3, base + 2),
            ]
    visual = trimesh.visual.TextureVisuals(uv=np.array(uv, float), image=Image.fromarray(texture))
    return trimesh.Trimesh(np.array(vertices), np.array(faces), visual=visual, process=False)


def look_at(eye: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-to-world in OpenGL axes (looking down -z, y up)."""
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross([0.0, 1.0, 0.0], back)
    right /= np.linalg.norm(right)
    pose = np.eye(4)
    pose[:3, :3] = np.stack([right, np.cross(back, right), back], axis=1)
    pose[:3, 3] = eye
    return pose


@dataclass
class RenderedCapture:
    width: int
    height: int
    K: np.ndarray  # 3x3, pixel centres at +0.5
    cam_to_world: list[np.ndarray] = field(default_factory=list)  # OpenCV axes, metres
    images: list[np.ndarray] = field(default_factory=list)  # RGB uint8
    depth: list[np.ndarray] = field(default_factory=list)  # metres, 0 = nothing
    masks: list[dict[str, np.ndarray]] = field(default_factory=list)  # object name -> visible mask

    @property
    def names(self) -> list[str]:
        return [f"frame_{k:05d}.png" for k in range(len(self.images))]


def _upload_textures_on_any_python(pyrender) -> None:
    """pyrender pins PyOpenGL 3.1.0, whose ``glGenTextures(n)`` passes a ``byref`` that Python 3.13's
    ctypes no longer converts (``No array-type handler for type _ctypes.type``): the one GL call
    pyrender makes only for textures. Generate the names through the raw entry point with a ctypes
    array, which every PyOpenGL and Python accept. Only this fixture draws textures."""
    from OpenGL.raw.GL.VERSION.GL_1_1 import glGenTextures

    def gen_textures(count: int):
        names = (ctypes.c_uint * count)()
        glGenTextures(count, names)
        return names[0] if count == 1 else list(names)

    pyrender.texture.glGenTextures = gen_textures


def render_capture(num_frames: int = 24, width: int = 640, height: int = 480, seed: int = 0) -> RenderedCapture:
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    import pyrender

    _upload_textures_on_any_python(pyrender)

    rng = np.random.default_rng(seed)
    scene = pyrender.Scene(ambient_light=np.ones(3), bg_color=np.zeros(4))
    nodes = {}
    for centre, size in ROOM:
        scene.add(pyrender.Mesh.from_trimesh(textured_box(centre, size, noise_texture(rng))))
    for name, _, boxes in OBJECTS:
        texture = noise_texture(rng)
        mesh = trimesh.util.concatenate([textured_box(c, s, texture) for c, s in boxes])
        nodes[name] = scene.add(pyrender.Mesh.from_trimesh(mesh))
    f = 0.8 * width
    K = np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
    camera = scene.add(pyrender.IntrinsicsCamera(f, f, width / 2, height / 2, znear=0.05, zfar=20.0))
    # the process-wide cached renderer: deleting a pyrender EGL renderer terminates the EGL display,
    # and with it the contexts of every other renderer in the process (later tests would fail)
    renderer = renderer_for(width, height)
    out = RenderedCapture(width, height, K)
    target = np.array([0.35, 0.5, 0.2])
    colours = {name: np.array([60 * (k + 1), 0, 0], np.uint8) for k, name in enumerate(nodes)}
    for angle in np.radians(np.linspace(-50.0, 50.0, num_frames)):
        eye = target + np.array([2.6 * np.sin(angle), 0.9, 2.6 * np.cos(angle)])
        pose_gl = look_at(eye, target)
        scene.set_pose(camera, pose_gl)
        rgb, depth = renderer.render(scene, flags=pyrender.RenderFlags.FLAT)
        seg, _ = renderer.render(
            scene, flags=pyrender.RenderFlags.SEG, seg_node_map={n: colours[k] for k, n in nodes.items()}
        )
        out.cam_to_world.append(pose_gl @ OPENGL_TO_OPENCV)
        out.images.append(np.ascontiguousarray(rgb[..., :3]))
        out.depth.append(depth.astype(np.float64))
        out.masks.append({name: seg[..., 0] == colours[name][0] for name in nodes})
    return out


def _write_frames(capture: RenderedCapture, folder: Path, depth: bool = True) -> None:
    (folder / "images").mkdir(parents=True, exist_ok=True)
    if depth:
        (folder / "depth").mkdir(exist_ok=True)
    for name, rgb, metres in zip(capture.names, capture.images, capture.depth, strict=True):
        cv2.imwrite(str(folder / "images" / name), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        if depth:
            cv2.imwrite(str(folder / "depth" / name), np.round(metres * 1000).astype(np.uint16))


def write_transforms(capture: RenderedCapture, folder: Path, seed: int = 0, depth: bool = True) -> None:
    """nerfstudio's layout: transforms.json (frames in random order, OpenGL poses), images/, depth/."""
    _write_frames(capture, folder, depth)
    order = np.random.default_rng(seed).permutation(len(capture.names))
    frames = []
    for k in order:
        entry = {
            "file_path": f"images/{capture.names[k]}",
            "transform_matrix": (capture.cam_to_world[k] @ OPENGL_TO_OPENCV).tolist(),
        }
        if depth:
            entry["depth_file_path"] = f"depth/{capture.names[k]}"
        frames.append(entry)
    fx, fy, cx, cy = capture.K[0, 0], capture.K[1, 1], capture.K[0, 2], capture.K[1, 2]
    data = {
        "camera_model": "OPENCV",
        "fl_x": fx,
        "fl_y": fy,
        "cx": cx,
        "cy": cy,
        "w": capture.width,
        "h": capture.height,
        "k1": 0.0,
        "k2": 0.0,
        "p1": 0.0,
        "p2": 0.0,
        "frames": frames,
    }
    (folder / "transforms.json").write_text(json.dumps(data, indent=1))


def write_colmap_text(
    capture: RenderedCapture, folder: Path, unit: float, seed: int = 0, points_per_frame: int = 300
) -> None:
    """A COLMAP text model in ``folder/sparse/0`` whose world is in units of ``unit`` metres, images/, depth/.

    Sparse points are surface points sampled from each frame's depth, each seen by that frame only.
    """
    _write_frames(capture, folder)
    rng = np.random.default_rng(seed)
    model = folder / "sparse" / "0"
    model.mkdir(parents=True)
    fx, fy, cx, cy = (float(v) for v in (capture.K[0, 0], capture.K[1, 1], capture.K[0, 2], capture.K[1, 2]))
    (model / "cameras.txt").write_text(f"1 PINHOLE {capture.width} {capture.height} {fx!r} {fy!r} {cx!r} {cy!r}\n")
    images, points = [], []
    for k, (name, pose, metres) in enumerate(zip(capture.names, capture.cam_to_world, capture.depth, strict=True)):
        world_to_cam = np.linalg.inv(pose)
        rows, cols = np.nonzero(metres > 0)
        pick = rng.choice(rows.size, min(points_per_frame, rows.size), replace=False)
        uv = np.stack([cols[pick] + 0.5, rows[pick] + 0.5], axis=1)
        z = metres[rows[pick], cols[pick]]
        cam = np.stack([(uv[:, 0] - cx) / fx * z, (uv[:, 1] - cy) / fy * z, z], axis=1)
        world = cam @ pose[:3, :3].T + pose[:3, 3]
        observations = []
        for j in range(len(uv)):
            pid = len(points) + 1
            points.append(f"{pid} {' '.join(repr(float(v)) for v in world[j] / unit)} 128 128 128 0.5 {k + 1} {j}")
            observations.append(f"{float(uv[j, 0])!r} {float(uv[j, 1])!r} {pid}")
        x, y, zq, w = (float(v) for v in Rotation.from_matrix(world_to_cam[:3, :3]).as_quat())
        t = [float(v) for v in world_to_cam[:3, 3] / unit]
        images.append(f"{k + 1} {w!r} {x!r} {y!r} {zq!r} {t[0]!r} {t[1]!r} {t[2]!r} 1 {name}\n{' '.join(observations)}")
    (model / "images.txt").write_text("\n".join(images) + "\n")
    (model / "points3D.txt").write_text("\n".join(points) + "\n")


def rle(mask: np.ndarray) -> dict:
    encoded = mask_utils.encode(np.asfortranarray(mask.astype(np.uint8)))
    return {"size": encoded["size"], "counts": encoded["counts"].decode("ascii")}


def write_detections(capture: RenderedCapture, folder: Path, seed: int = 0) -> None:
    """usl-segment's output for the capture's frames, in random order: the true visible masks (scores
    0.8..1), and decoys: a low-score chair (0.3) and a confident person on the wall in every frame."""
    rng = np.random.default_rng(seed)
    coco = {name: coco_id for name, coco_id, _ in OBJECTS}
    decoy = np.zeros((capture.height, capture.width), bool)
    decoy[: capture.height // 6, : capture.width // 5] = True
    results = []
    for k, (name, masks) in enumerate(zip(capture.names, capture.masks, strict=True)):
        # usl-segment writes file names as given on its command line: relative or absolute
        file_name = f"images/{name}" if k % 2 else str((folder / "images" / name).resolve())
        for obj, mask in masks.items():
            if mask.any():
                results.append(
                    {
                        "image_id": k,
                        "file_name": file_name,
                        "category_id": coco[obj],
                        "score": float(rng.uniform(0.8, 1.0)),
                        "segmentation": rle(mask),
                    }
                )
        results.append(
            {"image_id": k, "file_name": name, "category_id": CHAIR_COCO, "score": 0.3, "segmentation": rle(decoy)}
        )
        results.append(
            {"image_id": k, "file_name": name, "category_id": PERSON_COCO, "score": 0.95, "segmentation": rle(decoy)}
        )
    order = rng.permutation(len(results))
    (folder / "detections.json").write_text(json.dumps([results[k] for k in order]))
