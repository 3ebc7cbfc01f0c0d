"""``usl-predict``: 3D objects from single images with a trained model.

    usl-predict --checkpoint run/ --K intrinsics.txt photo.jpg   # or --fov 60 instead of --K

For each image it writes ``<name>.glb`` (one mesh per detected object, named ``<index>_<category>``,
in the camera frame) -- plus ``.obj`` and/or ``.ply`` with ``--formats`` -- and ``<name>_overlay.png``
(the meshes rendered over the image, with boxes and scores).

Coordinates are the OpenCV camera frame of DESIGN.md §2 (x right, y down, z forward, metres);
``--axes opengl`` flips y and z for viewers that expect y up. ``K`` follows DESIGN.md §2 too (pixel
centres at +0.5); a K from an OpenCV calibration (integer pixel centres) needs ``--opencv-k``.
A PLY holds one mesh, so it contains all objects merged, each with its own vertex colour.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Callable, Sequence

import cv2
import numpy as np
import torch
import trimesh

from usl.data.frames import FrameData
from usl.engine.eval_model import ModelPredictor, load_checkpoint_model
from usl.engine.eval_types import EvalInput
from usl.engine.visualize import draw_boxes, palette, render_overlay, write_png
from usl.geometry.cameras import intrinsics_from_fov, opencv_to_opengl_camera
from usl.model.outputs import ObjectPredictions
from usl.records import UslError

FORMATS = ("glb", "obj", "ply")
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
        scene_id=name, view_id=0, image=torch.from_numpy(image).permute(2, 0, 1).float().div_(255.0), K=K,
        cam_to_world=torch.eye(4, dtype=torch.float64), instance_ids=torch.zeros(0, dtype=torch.int64),
        labels=torch.zeros(0, dtype=torch.int64), boxes=torch.zeros(0, 4), masks=torch.zeros(0, height, width, dtype=torch.bool),
        depth_min=torch.zeros(0),
    )


def object_names(pred: ObjectPredictions, categories: Sequence[str]) -> list[str]:
    return [f"{n:02d}_{categories[int(l)].replace(' ', '_')}" for n, l in enumerate(pred.labels.tolist())]


def mesh_scene(pred: ObjectPredictions, categories: Sequence[str], axes: str = "opencv") -> trimesh.Scene:
    """A trimesh Scene with one named, coloured node per object."""
    flip = opencv_to_opengl_camera()[:3, :3].numpy() if axes == "opengl" else np.eye(3)
    faces = pred.faces.cpu().numpy()
    scene = trimesh.Scene()
    for name, verts, color in zip(object_names(pred, categories), pred.verts.cpu().double().numpy(), palette(len(pred))):
        mesh = trimesh.Trimesh(verts @ flip.T, faces, process=False)
        mesh.visual.vertex_colors = np.array([*color, 255], dtype=np.uint8)
        scene.add_geometry(mesh, node_name=name, geom_name=name)
    return scene


def write_meshes(scene: trimesh.Scene, stem: Path, formats: Sequence[str]) -> list[Path]:
    written = []
    for fmt in formats:
        path = stem.with_suffix(f".{fmt}")
        if fmt == "ply":
            trimesh.util.concatenate(list(scene.dump())).export(path)
        else:
            scene.export(path)
        written.append(path)
    return written


def predict_images(
    detect: Detect, image_paths: Sequence[str | Path], out_dir: str | Path, categories: Sequence[str],
    K: np.ndarray | None = None, fov_deg: float | None = None, formats: Sequence[str] = ("glb",),
    score_threshold: float = 0.5, axes: str = "opencv", opencv_k: bool = False,
) -> dict[str, list[Path]]:
    """Run ``detect`` on each image and write meshes and overlays; returns the files per image."""
    bad = [f for f in formats if f not in FORMATS]
    if bad:
        raise UslError(f"unknown mesh format(s) {bad}; choose from {', '.join(FORMATS)}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    images = [(Path(p), read_image(p)) for p in image_paths]  # fail on a bad path before any work
    written: dict[str, list[Path]] = {}
    stems: set[str] = set()
    for path, image in images:
        stem = path.stem if path.stem not in stems else f"{path.stem}_{len(stems)}"
        stems.add(stem)
        frame = image_frame(image, camera_for(image, K, fov_deg, opencv_k), stem)
        pred = detect(frame).to("cpu")
        pred = pred.select(pred.scores >= score_threshold)
        files = write_meshes(mesh_scene(pred, categories, axes), out / stem, formats) if len(pred) else []
        colors = palette(len(pred))
        overlay = render_overlay(image, pred.verts, pred.faces, frame.K, colors)
        texts = [f"{categories[int(l)]} {float(s):.2f}" for l, s in zip(pred.labels.tolist(), pred.scores.tolist())]
        files.append(write_png(out / f"{stem}_overlay.png", draw_boxes(overlay, pred.boxes, texts, colors)))
        written[str(path)] = files
    return written


def model_detector(checkpoint: str | Path, device: str) -> tuple[Detect, list[str]]:
    """The checkpoint's model in detection mode, and its category names."""
    model, config = load_checkpoint_model(checkpoint, device)
    predictor = ModelPredictor(model, int(config.data.max_size), "detections")
    return (lambda frame: predictor([EvalInput(frame, {})])[0]), list(config.model.categories)


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="usl-predict", description=__doc__.split("\n\n")[0])
    p.add_argument("images", nargs="+", help="input image file(s)")
    p.add_argument("--checkpoint", required=True, help="checkpoint file or training run folder")
    camera = p.add_mutually_exclusive_group(required=True)
    camera.add_argument("--K", dest="k_file", help="3x3 intrinsics for the images' resolution (text or JSON)")
    camera.add_argument("--fov", type=float, help="horizontal field of view in degrees (centred principal point)")
    p.add_argument("--opencv-k", action="store_true", help="K puts pixel centres at integers (OpenCV): shift by +0.5")
    p.add_argument("--out", default="predictions", help="output folder")
    p.add_argument("--formats", default="glb", help=f"comma-separated mesh formats from {', '.join(FORMATS)}")
    p.add_argument("--score-threshold", type=float, default=0.5, help="keep detections scoring at least this")
    p.add_argument("--axes", default="opencv", choices=("opencv", "opengl"), help="coordinate axes of the mesh files")
    p.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    return p.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    try:
        K = read_intrinsics(args.k_file) if args.k_file else None
        formats = [f.strip() for f in args.formats.split(",") if f.strip()]
        missing = [p for p in args.images if not Path(p).is_file()]
        if missing:  # checked before the model loads; predict_images decodes them all before any work
            raise UslError(f"image {missing[0]} does not exist" + (f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""))
        detect, categories = model_detector(args.checkpoint, args.device)
        written = predict_images(detect, args.images, args.out, categories, K, args.fov, formats,
                                 args.score_threshold, args.axes, args.opencv_k)
    except UslError as exc:
        print(f"usl-predict: error: {exc}", file=sys.stderr)
        return 2
    for image, files in written.items():
        print(f"{image}: {', '.join(str(f) for f in files)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
