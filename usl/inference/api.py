"""The Python API: a trained model on one image, the 3D objects as meshes, the scene as a file.

    import usl
    model = usl.load("runs/hypersim")                  # a run folder or a checkpoint file
    scene = model.predict(image, fov=60, score=0.5)   # a path or an (H, W, 3) RGB array; or K=3x3
    scene.objects[0].mesh, scene.objects[0].category  # trimesh.Trimesh in the scene's axes, "chair"
    scene.export("photo.glb")                          # .glb .html .obj .ply, as usl-predict writes them

Meshes are in glTF's axes by default (+Y up, the camera at the origin looking down -Z, metres),
the axes of the exported files; ``axes="opencv"`` keeps the camera frame (x right, y down, z
forward). Category ids are the dataset's own, as in its records and COCO export.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import trimesh

from usl.data.frames import CategoryIndex
from usl.errors import UslError
from usl.inference.gltf_scene import axes_matrix
from usl.inference.predict import (
    Detect,
    camera_for,
    image_frame,
    model_detector,
    overlay_picture,
    read_image,
    write_scene_file,
)
from usl.model.outputs import ObjectPredictions
from usl.vis.visualize import write_png


@dataclass(frozen=True)
class Object3D:
    """One predicted object."""

    mesh: trimesh.Trimesh  # in the scene's axes, metres
    category: str  # class name
    category_id: int  # the dataset's id of the class
    score: float  # detection score
    z: float  # depth of the object's centre along the optical axis (layout head), metres
    rho: float  # the object's extent in depth (layout head), metres
    box: tuple[float, float, float, float]  # 2D box x0, y0, x1, y1 in input pixels


@dataclass
class Scene:
    """The objects predicted from one image, with the image and its camera, ready to export."""

    objects: list[Object3D]
    image: np.ndarray  # (H, W, 3) RGB uint8
    K: np.ndarray  # (3, 3) intrinsics, pixel centres at +0.5
    axes: str  # "gltf" or "opencv": the axes of the meshes and of every exported file
    predictions: ObjectPredictions  # the raw tensors, OpenCV camera frame
    categories: CategoryIndex

    def export(self, path: str | Path) -> Path:
        """Write the scene; the suffix picks the format: ``.glb`` / ``.html`` (objects, camera, image),
        ``.obj`` / ``.ply`` (objects only) or ``.png`` (the objects drawn over the image)."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        if path.suffix.lower() == ".png":
            K = torch.from_numpy(self.K).float()
            return write_png(path, overlay_picture(self.predictions, self.categories, self.image, K))
        return write_scene_file(self.predictions, self.categories, self.image, self.K, path, self.axes)


class Model:
    """A trained USL model ready to predict (``usl.load``)."""

    def __init__(self, detect: Detect, categories: CategoryIndex):
        self._detect = detect
        self.categories = categories

    def predict(
        self,
        image: str | Path | np.ndarray,
        K: np.ndarray | None = None,
        fov: float | str = 60.0,
        score: float = 0.5,
        axes: str = "gltf",
    ) -> Scene:
        """The objects of ``image`` scoring at least ``score``.

        ``image``: a file path or an (H, W, 3) RGB array (uint8, or float in [0, 1]). The camera: ``K``
        (3x3, pixel centres at +0.5) if given, else a centred one with horizontal field of view
        ``fov`` degrees; ``fov="auto"`` reads it from the file's EXIF (60 degrees, with a warning,
        when there is none)."""
        path = Path(image) if isinstance(image, (str, Path)) else None
        pixels = read_image(path) if path is not None else _rgb_array(image)
        K_given = None if K is None else np.asarray(K, dtype=np.float64)
        if K_given is not None and K_given.shape != (3, 3):
            raise UslError(f"K must be a 3x3 matrix, got shape {K_given.shape}")
        frame = image_frame(pixels, camera_for(pixels, K_given, fov, path=path), path.stem if path else "image")
        with torch.no_grad():
            pred = self._detect(frame).to("cpu")
        pred = pred.select(pred.scores >= score)
        flip = axes_matrix(axes)
        objects = [
            Object3D(
                mesh=trimesh.Trimesh(verts @ flip.T, pred.faces.numpy(), process=False),
                category=self.categories.names[label],
                category_id=self.categories.ids[label],
                score=float(s),
                z=float(z),
                rho=float(rho),
                box=tuple(float(v) for v in box),
            )
            for verts, label, s, z, rho, box in zip(
                pred.verts.double().numpy(),
                pred.labels.tolist(),
                pred.scores.tolist(),
                pred.z.tolist(),
                pred.rho.tolist(),
                pred.boxes.tolist(),
                strict=True,
            )
        ]
        return Scene(objects, pixels, frame.K.double().numpy(), axes, pred, self.categories)


def _rgb_array(image: np.ndarray) -> np.ndarray:
    array = np.asarray(image)
    if array.ndim != 3 or array.shape[2] != 3:
        raise UslError(f"expected an (H, W, 3) RGB image, got an array of shape {array.shape}")
    if array.dtype == np.uint8:
        return np.ascontiguousarray(array)
    if np.issubdtype(array.dtype, np.floating) and array.size and 0.0 <= array.min() and array.max() <= 1.0:
        return (array * 255.0 + 0.5).astype(np.uint8)
    raise UslError(f"expected uint8 pixels or floats in [0, 1], got {array.dtype} in [{array.min()}, {array.max()}]")


def load(checkpoint: str | Path, device: str = "auto") -> Model:
    """The model of a training run folder (its latest checkpoint) or of a checkpoint file."""
    if device == "auto":
        device = "cuda" if torch.cuda.is_available() else "cpu"
    detect, categories = model_detector(checkpoint, device)
    return Model(detect, categories)
