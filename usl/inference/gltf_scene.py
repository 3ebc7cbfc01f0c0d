"""Predicted objects as a glTF-ready trimesh Scene, in glTF's own conventions.

glTF is +Y up, and a glTF camera looks down its local -Z; usl works in OpenCV camera axes (x right,
y down, z forward). With ``axes="gltf"`` (the default of ``usl-predict``) points are written as
``diag(1, -1, -1) @ X_opencv``, so every glTF viewer shows the scene upright and the camera node
sits at the origin with the identity pose. With ``axes="opencv"`` the points stay as they are and
the camera node carries the flip instead: the view through the camera is the same either way.

The scene holds one node per object (``<index>_<category>``; ``extras``: category name, the
dataset's category id (as in its records, manifest and COCO export), score, z, rho, box), a perspective camera matching the input view (``yfov`` from K and the image
height, ``aspectRatio`` from K and the width; glTF has no principal point, so the full K and the
image size are kept in the camera's ``extras``: ``{"K": 3x3 rows, "image_size": [W, H]}``, OpenCV
axes, pixel centres at +0.5) and the input image as a textured plane filling the camera's view
behind the objects (node ``input_image``). ``scene_glb`` writes the file with those extras.
"""

from __future__ import annotations

import json
import math
import struct
from typing import Any

import numpy as np
import torch
import trimesh
from PIL import Image

from usl.data.frames import CategoryIndex
from usl.geometry.cameras import opencv_to_opengl_camera, unproject
from usl.model.outputs import ObjectPredictions
from usl.vis.visualize import palette

AXES = ("gltf", "opencv")
CAMERA_NODE = "camera"
IMAGE_NODE = "input_image"


def axes_matrix(axes: str) -> np.ndarray:
    """3x3 taking OpenCV camera coordinates to the written coordinates."""
    if axes not in AXES:
        raise ValueError(f"axes must be one of {AXES}, got {axes!r}")
    return opencv_to_opengl_camera()[:3, :3].numpy() if axes == "gltf" else np.eye(3)


def object_names(pred: ObjectPredictions, categories: CategoryIndex) -> list[str]:
    return [f"{n:02d}_{categories.names[int(l)].replace(' ', '_')}" for n, l in enumerate(pred.labels.tolist())]


def object_meshes(
    pred: ObjectPredictions, categories: CategoryIndex, axes: str, material: bool = False
) -> trimesh.Scene:
    """One named, coloured node per object, its category and score in the node's ``extras``.

    Colours are vertex colours (what OBJ and PLY keep) or, with ``material``, a matte glTF material:
    a glTF mesh without a material is fully metallic, which shows black under diffuse light."""
    flip = axes_matrix(axes)
    faces = pred.faces.cpu().numpy()
    scene = trimesh.Scene()
    objects = zip(
        object_names(pred, categories),
        pred.verts.cpu().double().numpy(),
        palette(len(pred)),
        pred.labels.tolist(),
        pred.scores.tolist(),
        pred.z.tolist(),
        pred.rho.tolist(),
        pred.boxes.tolist(),
        strict=True,
    )
    for name, verts, color, label, score, z, rho, box in objects:
        mesh = trimesh.Trimesh(verts @ flip.T, faces, process=False)
        if material:
            mesh.visual = trimesh.visual.TextureVisuals(
                material=trimesh.visual.material.PBRMaterial(
                    name=name, baseColorFactor=[*color, 255], metallicFactor=0.0, roughnessFactor=0.8
                )
            )
        else:
            mesh.visual.vertex_colors = np.array([*color, 255], dtype=np.uint8)
        extras = {
            "category": categories.names[int(label)],
            "category_id": categories.ids[int(label)],  # the dataset's id, as in its records and COCO export
            "score": round(float(score), 6),
            "z": float(z),
            "rho": float(rho),
            "box_xyxy": [round(float(v), 3) for v in box],
        }
        scene.add_geometry(mesh, node_name=name, geom_name=name, metadata=extras)
    return scene


def gltf_camera(K: np.ndarray, width: int, height: int) -> trimesh.scene.Camera:
    """A perspective camera with K's vertical field of view and pixel aspect.

    trimesh writes ``aspectRatio = fov[0] / fov[1]`` and reads ``fov = (aspectRatio * yfov, yfov)``,
    so ``fov[0]`` is set to aspect * yfov for the file to hold glTF's ``aspectRatio``."""
    fx, fy = float(K[0, 0]), float(K[1, 1])
    yfov = math.degrees(2.0 * math.atan(0.5 * height / fy))
    aspect = (width * fy) / (height * fx)
    return trimesh.scene.Camera(name=CAMERA_NODE, fov=(aspect * yfov, yfov), resolution=(width, height), z_near=0.01)


def image_plane(image: np.ndarray, K: np.ndarray, depth: float, axes: str) -> trimesh.Trimesh:
    """The image on a quad at planar ``depth``, exactly covering the camera's view (full K)."""
    height, width = image.shape[:2]
    corners = torch.tensor([[0.0, 0.0], [width, 0.0], [width, height], [0.0, height]], dtype=torch.float64)
    points = unproject(corners, torch.full((4,), float(depth), dtype=torch.float64), torch.from_numpy(K).double())
    uv = np.array([[0.0, 1.0], [1.0, 1.0], [1.0, 0.0], [0.0, 0.0]])  # trimesh's uv origin is bottom-left
    material = trimesh.visual.material.PBRMaterial(
        baseColorTexture=Image.fromarray(image), doubleSided=True, metallicFactor=0.0, roughnessFactor=1.0
    )
    faces = np.array([[0, 2, 1], [0, 3, 2]])  # facing the camera (-z in OpenCV axes)
    return trimesh.Trimesh(
        points.numpy() @ axes_matrix(axes).T,
        faces,
        process=False,
        visual=trimesh.visual.TextureVisuals(uv=uv, material=material),
    )


def prediction_scene(
    pred: ObjectPredictions, categories: CategoryIndex, image: np.ndarray, K: np.ndarray, axes: str = "gltf"
) -> trimesh.Scene:
    """Objects, the input camera and the image plane (behind the farthest object)."""
    scene = object_meshes(pred, categories, axes, material=True)
    height, width = image.shape[:2]
    depth = 1.25 * float(pred.verts[..., 2].max()) if len(pred) else 1.0
    scene.add_geometry(
        image_plane(image, K, max(depth, 1e-3), axes),
        node_name=IMAGE_NODE,
        geom_name=IMAGE_NODE,
        metadata={"depth_m": depth},
    )
    scene.camera = gltf_camera(K, width, height)
    pose = np.eye(4)
    pose[:3, :3] = axes_matrix(axes) @ opencv_to_opengl_camera()[:3, :3].numpy()  # glTF camera frame -> written frame
    scene.camera_transform = pose
    return scene


def camera_extras(K: np.ndarray, width: int, height: int) -> dict[str, Any]:
    """What glTF's camera cannot say: the full K (off-centre principal point, skew) and the image size."""
    return {"K": [[float(v) for v in row] for row in np.asarray(K, dtype=np.float64)], "image_size": [width, height]}


def scene_glb(scene: trimesh.Scene, K: np.ndarray, width: int, height: int) -> bytes:
    """The scene as GLB bytes, with what trimesh does not write: ``camera_extras`` on the camera, and
    the image plane's material unlit (``KHR_materials_unlit``), so viewers show the image's own
    colours rather than shading it by their lights."""
    return finish_glb(scene.export(file_type="glb"), camera_extras(K, width, height))


ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER = 34962, 34963  # glTF bufferView targets: vertex data, indices


def _set_buffer_view_targets(tree: dict[str, Any]) -> None:
    """Mark the buffer views of vertex attributes and indices as such (trimesh leaves them unset; the
    Khronos validator hints at it, and some loaders upload such views only when marked)."""
    for mesh in tree.get("meshes", []):
        for primitive in mesh["primitives"]:
            uses = [(a, ARRAY_BUFFER) for a in primitive["attributes"].values()]
            uses += [(primitive["indices"], ELEMENT_ARRAY_BUFFER)] if "indices" in primitive else []
            for accessor, target in uses:
                view = tree["accessors"][accessor].get("bufferView")
                if view is not None:
                    tree["bufferViews"][view]["target"] = target


def finish_glb(glb: bytes, extras: dict[str, Any]) -> bytes:
    """``extras`` added to the first camera, the ``IMAGE_NODE`` mesh's materials made unlit, buffer
    view targets set: the JSON chunk is rewritten, the binary one kept."""
    magic, version, _ = struct.unpack_from("<4sII", glb, 0)
    json_length, json_type = struct.unpack_from("<I4s", glb, 12)
    if magic != b"glTF" or version != 2 or json_type != b"JSON":
        raise ValueError("not a glTF 2.0 binary with its JSON chunk first")
    tree = json.loads(glb[20 : 20 + json_length])
    tree["cameras"][0].setdefault("extras", {}).update(extras)
    _set_buffer_view_targets(tree)
    for node in tree["nodes"]:
        if node.get("name") == IMAGE_NODE and "mesh" in node:
            for primitive in tree["meshes"][node["mesh"]]["primitives"]:
                material = tree["materials"][primitive["material"]]
                material.setdefault("extensions", {})["KHR_materials_unlit"] = {}
                tree["extensionsUsed"] = sorted({*tree.get("extensionsUsed", []), "KHR_materials_unlit"})
    text = json.dumps(tree, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)  # chunks are 4-byte aligned; JSON pads with spaces
    rest = glb[20 + json_length :]
    total = 12 + 8 + len(text) + len(rest)
    return struct.pack("<4sII", b"glTF", 2, total) + struct.pack("<I4s", len(text), b"JSON") + text + rest
