"""``usl-predict``: 3D objects from single images with a trained model (the library behind
``usl.cli.predict``).

For each image it writes ``<name>.glb`` -- one mesh per detected object, the input camera and the
image as a textured plane, in glTF's +Y-up axes (``usl.inference.gltf_scene``) -- plus ``.obj``,
``.ply`` (objects only) and ``.html`` (a self-contained 3D viewer of the GLB) with ``--formats``,
and ``<name>_overlay.png`` (the meshes rendered over the image, with boxes and scores).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np
import torch
import trimesh

from usl.data.frames import FrameData
from usl.evaluation.model import ModelPredictor, load_checkpoint_model
from usl.evaluation.types import EvalInput
from usl.inference.gltf_scene import object_meshes, prediction_scene
from usl.inference.formats import FORMATS
from usl.vis.visualize import draw_boxes, palette, render_overlay, write_png
from usl.geometry.cameras import intrinsics_from_fov
from usl.model.outputs import ObjectPredictions
from usl.errors import UslError

Detect = Callable[[FrameData], ObjectPredictions]


def read_intrinsics(path: str | Path) -> np.ndarray:
    """A 3x3 K from a text file (9 numbers, e.g. ``np.savetxt``) or JSON (a 3x3 / 9-list, or ``{"K": ...}``)."""
    path = Path(path)
    if not path.is_file():
        raise UslError(f"K file {path} does not exist")
    text = path.read_text()
    try:
        if path.suffix.lower() == ".json":
            data = json.loads(text)
            values = np.asarray(data["K"] if isinstance(data, dict) else data, dtype=np.float64)
        else:
            values = np.asarray(text.replace(",", " ").split(), dtype=np.float64)
    except (ValueError, KeyError, TypeError) as exc:
        raise UslError(f"K file {path}: cannot read a 3x3 matrix ({type(exc).__name__}: {exc})") from exc
    if values.size != 9:
        raise UslError(f"K file {path}: expected 9 numbers (a 3x3 matrix), got {values.size}")
    K = values.reshape(3, 3)
    if not np.isfinite(K).all() or abs(np.linalg.det(K)) < 1e-12:
        raise UslError(f"K file {path}: the matrix is not finite and invertible: {K.tolist()}")
    return K


def read_image(path: str | Path) -> np.ndarray:
    """(H, W, 3) RGB uint8."""
    path = Path(path)
    if not path.is_file():
        raise UslError(f"image {path} does not exist")
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise UslError(f"image {path} could not be decoded (not an image format OpenCV reads)")
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


def camera_for(image: np.ndarray, K: np.ndarray | None, fov_deg: float | None, opencv_k: bool) -> torch.Tensor:
    height, width = image.shape[:2]
    if K is None:
        if fov_deg is None or not 0.0 < fov_deg < 180.0:
            raise UslError(f"need --K or a horizontal --fov in (0, 180) degrees, got {fov_deg}")
        return intrinsics_from_fov(math.radians(fov_deg), width, height).float()
    K = K.copy()
    if opencv_k:
        K[:2] += 0.5 * K[2:3]  # principal point (and any projective row) moves by half a pixel
    return torch.from_numpy(K).float()


def image_frame(image: np.ndarray, K: torch.Tensor, name: str) -> FrameData:
    """An unannotated input view for the model."""
    height, width = image.shape[:2]
    return FrameData(
        scene_id=name,
        view_id=0,
        image=torch.from_numpy(image).permute(2, 0, 1).float().div_(255.0),
        K=K,
        cam_to_world=torch.eye(4, dtype=torch.float64),
        instance_ids=torch.zeros(0, dtype=torch.int64),
        labels=torch.zeros(0, dtype=torch.int64),
        boxes=torch.zeros(0, 4),
        masks=torch.zeros(0, height, width, dtype=torch.bool),
        depth_min=torch.zeros(0),
    )


@dataclass
class ImageResult:
    """What ``predict_images`` made of one image."""

    files: list[Path] = field(default_factory=list)
    num_objects: int = 0  # detections at or above the threshold
    best_score: float | None = None  # highest detection score of all (None: no detection at all)


def write_meshes(
    pred: ObjectPredictions,
    categories: Sequence[str],
    image: np.ndarray,
    K: np.ndarray,
    stem: Path,
    formats: Sequence[str],
    axes: str,
) -> list[Path]:
    """GLB and HTML hold the whole scene (objects, camera, image plane); OBJ and PLY the objects only."""
    written = []
    for fmt in formats:
        path = stem.with_suffix(f".{fmt}")
        if fmt in ("glb", "html"):
            scene = prediction_scene(pred, categories, image, K, axes)
            if fmt == "glb":
                scene.export(path)
            else:
                from trimesh.viewer.notebook import scene_to_html  # three.js bundled into the page: no network

                path.write_text(scene_to_html(scene))
        elif fmt == "ply":  # a PLY holds one mesh: all objects merged, each with its own vertex colour
            trimesh.util.concatenate(list(object_meshes(pred, categories, axes).dump())).export(path)
        else:
            object_meshes(pred, categories, axes).export(path)
        written.append(path)
    return written


def predict_images(
    detect: Detect,
    image_paths: Sequence[str | Path],
    out_dir: str | Path,
    categories: Sequence[str],
    K: np.ndarray | None = None,
    fov_deg: float | None = None,
    formats: Sequence[str] = ("glb",),
    score_threshold: float = 0.5,
    axes: str = "gltf",
    opencv_k: bool = False,
) -> dict[str, ImageResult]:
    """Run ``detect`` on each image and write meshes and overlays; returns what was made per image."""
    bad = [f for f in formats if f not in FORMATS]
    if bad:
        raise UslError(f"unknown mesh format(s) {bad}; choose from {', '.join(FORMATS)}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    images = [(Path(p), read_image(p)) for p in image_paths]  # fail on a bad path before any work
    written: dict[str, ImageResult] = {}
    stems: set[str] = set()
    for path, image in images:
        stem = path.stem if path.stem not in stems else f"{path.stem}_{len(stems)}"
        stems.add(stem)
        frame = image_frame(image, camera_for(image, K, fov_deg, opencv_k), stem)
        pred = detect(frame).to("cpu")
        best = float(pred.scores.max()) if len(pred) else None
        pred = pred.select(pred.scores >= score_threshold)
        K_image = frame.K.double().numpy()
        files = write_meshes(pred, categories, image, K_image, out / stem, formats, axes) if len(pred) else []
        colors = palette(len(pred))
        overlay = render_overlay(image, pred.verts, pred.faces, frame.K, colors)
        texts = [f"{categories[int(l)]} {float(s):.2f}" for l, s in zip(pred.labels.tolist(), pred.scores.tolist())]
        files.append(write_png(out / f"{stem}_overlay.png", draw_boxes(overlay, pred.boxes, texts, colors)))
        written[str(path)] = ImageResult(files, len(pred), best)
    return written


def model_detector(checkpoint: str | Path, device: str) -> tuple[Detect, list[str]]:
    """The checkpoint's model in detection mode, and its category names."""
    model, config = load_checkpoint_model(checkpoint, device)
    predictor = ModelPredictor(model, int(config.data.max_size), "detections")
    return (lambda frame: predictor([EvalInput(frame, {})])[0]), list(config.model.categories)
