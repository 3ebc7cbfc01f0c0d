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
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import torch
import trimesh

from data_specs import DATASETS, load_dataset_spec
from usl.data.frames import CategoryIndex, FrameData
from usl.errors import UslError
from usl.evaluation.model import ModelPredictor, load_checkpoint_model
from usl.evaluation.types import EvalInput
from usl.geometry.cameras import intrinsics_from_fov, scale_intrinsics
from usl.inference.field_of_view import auto_fov_deg
from usl.inference.formats import FORMATS
from usl.inference.gltf_scene import object_meshes, prediction_scene, scene_glb
from usl.inference.gltf_viewer import viewer_html
from usl.model.config import ModelConfig
from usl.model.outputs import ObjectPredictions
from usl.records.names import check_name
from usl.vis.visualize import draw_boxes, palette, render_overlay, write_png

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


def camera_for(
    image: np.ndarray,
    K: np.ndarray | None,
    fov_deg: float | str | None,
    opencv_k: bool = False,
    path: str | Path | None = None,
) -> torch.Tensor:
    """K of ``image``: the given one, or a centred one of horizontal field of view ``fov_deg``
    (``"auto"``: from the EXIF of the file at ``path``, ``usl.inference.field_of_view``)."""
    height, width = image.shape[:2]
    if K is None:
        if fov_deg == "auto":
            fov_deg = auto_fov_deg(path, width, height)
        if not isinstance(fov_deg, (int, float)) or not 0.0 < fov_deg < 180.0:
            raise UslError(f"need K or a horizontal field of view in (0, 180) degrees or 'auto', got {fov_deg!r}")
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


def write_scene_file(
    pred: ObjectPredictions, categories: CategoryIndex, image: np.ndarray, K: np.ndarray, path: Path, axes: str
) -> Path:
    """One file, its format from the suffix. GLB and HTML hold the whole scene (objects, camera, image
    plane) and keep each object a node with its category and score. OBJ gives each object its own
    ``o`` group and material (``<stem>.mtl`` beside it), which is what trimesh splits a file by. PLY
    holds one mesh: the objects merged, each with its own vertex colour."""
    fmt = path.suffix.lower().lstrip(".")
    if fmt not in FORMATS:
        raise UslError(f"{path}: unknown scene format {fmt!r}; choose from {', '.join(FORMATS)}")
    if fmt in ("glb", "html"):
        glb = scene_glb(prediction_scene(pred, categories, image, K, axes), K, image.shape[1], image.shape[0])
        if fmt == "glb":
            path.write_bytes(glb)
        else:
            path.write_text(viewer_html(glb, title=path.stem))
    elif fmt == "ply":
        trimesh.util.concatenate(list(object_meshes(pred, categories, axes).dump())).export(path)
    else:
        scene = object_meshes(pred, categories, axes, material=True)
        text, files = trimesh.exchange.obj.export_obj(scene, return_texture=True, mtl_name=f"{path.stem}.mtl")
        path.write_text(text)
        for name, data in files.items():
            (path.parent / name).write_bytes(data)
    return path


OVERLAY_MIN_SIZE = 512  # overlays are drawn at least this large on the short side, so labels leave room


def overlay_picture(pred: ObjectPredictions, categories: CategoryIndex, image: np.ndarray, K: torch.Tensor):
    """The meshes rendered over the image with boxes, names and scores, upscaled to ``OVERLAY_MIN_SIZE``."""
    scale = max(1.0, OVERLAY_MIN_SIZE / min(image.shape[:2]))
    if scale > 1.0:
        size = (round(image.shape[1] * scale), round(image.shape[0] * scale))
        sx, sy = size[0] / image.shape[1], size[1] / image.shape[0]
        image = cv2.resize(image, size, interpolation=cv2.INTER_CUBIC)
        K = scale_intrinsics(K.double(), sx, sy).float()
        pred = replace(pred, boxes=pred.boxes * torch.tensor([sx, sy, sx, sy]))
    colors = palette(len(pred))
    overlay = render_overlay(image, pred.verts, pred.faces, K, colors)
    texts = [
        f"{categories.names[int(l)]} {float(s):.2f}"
        for l, s in zip(pred.labels.tolist(), pred.scores.tolist(), strict=True)
    ]
    return draw_boxes(overlay, pred.boxes, texts, colors)


def predict_images(
    detect: Detect,
    image_paths: Sequence[str | Path],
    out_dir: str | Path,
    categories: CategoryIndex,
    K: np.ndarray | None = None,
    fov_deg: float | str | None = None,
    formats: Sequence[str] = ("glb",),
    score_threshold: float = 0.5,
    axes: str = "gltf",
    opencv_k: bool = False,
) -> dict[str, ImageResult]:
    """Run ``detect`` on each image and write meshes and overlays; returns what was made per image."""
    bad = [f for f in formats if f not in FORMATS]
    if bad:
        raise UslError(f"unknown mesh format(s) {bad}; choose from {', '.join(FORMATS)}")
    for image_path in image_paths:  # an image's name names its output files
        check_name(Path(image_path).stem, "image name", image_path)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    images = [(Path(p), read_image(p)) for p in image_paths]  # fail on a bad path before any work
    written: dict[str, ImageResult] = {}
    stems: set[str] = set()
    for path, image in images:
        stem = path.stem if path.stem not in stems else f"{path.stem}_{len(stems)}"
        stems.add(stem)
        frame = image_frame(image, camera_for(image, K, fov_deg, opencv_k, path), stem)
        pred = detect(frame).to("cpu")
        best = float(pred.scores.max()) if len(pred) else None
        pred = pred.select(pred.scores >= score_threshold)
        K_image = frame.K.double().numpy()
        files = (
            [write_scene_file(pred, categories, image, K_image, out / f"{stem}.{f}", axes) for f in formats]
            if len(pred)
            else []
        )
        files.append(write_png(out / f"{stem}_overlay.png", overlay_picture(pred, categories, image, frame.K)))
        written[str(path)] = ImageResult(files, len(pred), best)
    return written


def model_detector(checkpoint: str | Path, device: str) -> tuple[Detect, CategoryIndex]:
    """The checkpoint's model in detection mode, and its categories (names and dataset ids)."""
    model, config = load_checkpoint_model(checkpoint, device)
    predictor = ModelPredictor(model, int(config.data.max_size), "detections")
    return (lambda frame: predictor([EvalInput(frame, {})])[0]), model_categories(config.model)


def model_categories(model_config: ModelConfig) -> CategoryIndex:
    """Names and dataset ids of the model's classes. Checkpoints written before ``model.category_ids``
    existed take the ids of the dataset spec with the same category names."""
    names = list(model_config.categories)
    ids = list(model_config.category_ids)
    if not ids:
        specs = [load_dataset_spec(name)["categories"] for name in DATASETS]
        ids = next(([int(c["id"]) for c in spec] for spec in specs if [c["name"] for c in spec] == names), [])
    if len(ids) != len(names):
        raise UslError(
            f"the checkpoint's model.category_ids {ids} do not match its {len(names)} model.categories {names}"
        )
    return CategoryIndex([{"id": i, "name": n} for i, n in zip(ids, names, strict=True)])
