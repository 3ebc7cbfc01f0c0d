"""Pictures of predictions, drawn with OpenCV and numpy (RGB uint8 arrays throughout).

* ``draw_boxes``: the input image with 2D boxes, category names and scores.
* ``render_overlay``: predicted meshes rendered (hard z-buffer, shaded by surface normals from the
  depth map) over an image; used by ``usl-predict`` and the evaluation pictures.
* ``mask_pair``: a view's true masks next to the predicted meshes rendered into that view.
* ``legend``: a panel of colour swatches and one line of text each (which object is which, and
  how it scored).
* ``birds_eye``: the layout seen from above the input camera: the x (right) / z (forward) plane of
  the input camera frame, objects as filled footprints (convex hull of their vertices), true
  objects outlined in white when known, cameras as wedges (input camera in yellow). The input
  camera's frame is used because datasets disagree on the world's up axis.
Colours follow the object index, so one object has one colour in every panel.
"""

from __future__ import annotations

import colorsys
from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np
import torch

from usl.errors import UslError
from usl.geometry import Meshes
from usl.geometry.cameras import unproject
from usl.render import HardRender, rasterize_hard

Tensor = torch.Tensor
GRAY = (128, 128, 128)
FONT = cv2.FONT_HERSHEY_SIMPLEX


def palette(n: int) -> list[tuple[int, int, int]]:
    """n well-separated saturated colours (golden-ratio hue steps), RGB 0-255."""
    return [tuple(int(255 * c) for c in colorsys.hsv_to_rgb((0.1 + i * 0.618034) % 1.0, 0.75, 0.95)) for i in range(n)]


def to_uint8(image: Tensor | np.ndarray) -> np.ndarray:
    """(3, H, W) float [0, 1] tensor or (H, W, 3) array -> contiguous (H, W, 3) uint8."""
    if isinstance(image, torch.Tensor):
        image = image.detach().cpu().permute(1, 2, 0).numpy()
    if image.dtype != np.uint8:
        image = np.clip(np.asarray(image, dtype=np.float32) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    return np.ascontiguousarray(image)


def draw_boxes(
    image: np.ndarray, boxes: Tensor, texts: Sequence[str], colors: Sequence[tuple[int, int, int]]
) -> np.ndarray:
    out = image.copy()
    thickness = max(1, round(min(out.shape[:2]) / 300))
    scale = max(0.35, min(out.shape[:2]) / 900)
    for box, text, color in zip(boxes.tolist(), texts, colors, strict=True):
        x0, y0, x1, y1 = (int(round(v)) for v in box)
        cv2.rectangle(out, (x0, y0), (x1 - 1, y1 - 1), color, thickness, cv2.LINE_AA)
        (tw, th), base = cv2.getTextSize(text, FONT, scale, 1)
        ty = max(y0, th + base)
        cv2.rectangle(out, (x0, ty - th - base), (x0 + tw, ty), color, -1)
        cv2.putText(out, text, (x0, ty - base), FONT, scale, (0, 0, 0), 1, cv2.LINE_AA)
    return out


def render_meshes(verts: Tensor, faces: Tensor, K: Tensor, height: int, width: int) -> HardRender:
    """Hard render of N meshes (N, V, 3) given in the camera frame of one view with intrinsics K."""
    meshes = Meshes.from_shared_topology(verts.float(), faces)
    return rasterize_hard(
        meshes.verts_packed(),
        meshes.faces_packed(),
        meshes.faces_packed_to_mesh_idx(),
        K.float().to(verts.device),
        height,
        width,
        num_meshes=verts.shape[0],
    )


def _normal_shading(depth: Tensor, K: Tensor) -> np.ndarray:
    """Lambert-like shading in [0.3, 1] from normals of the back-projected depth map (background 0)."""
    height, width = depth.shape
    v, u = torch.meshgrid(torch.arange(height) + 0.5, torch.arange(width) + 0.5, indexing="ij")
    finite = torch.isfinite(depth.cpu())
    d = torch.where(finite, depth.cpu().double(), torch.ones(()).double())
    points = unproject(torch.stack([u, v], -1).double(), d, K.cpu().double()).numpy()
    du, dv = np.gradient(points, axis=1), np.gradient(points, axis=0)
    normal = np.cross(du, dv)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True) + 1e-12
    view = points / (np.linalg.norm(points, axis=-1, keepdims=True) + 1e-12)
    shade = 0.3 + 0.7 * np.abs((normal * view).sum(-1))
    return np.where(finite.numpy(), shade, 0.0)


def render_overlay(
    image: np.ndarray,
    verts: Tensor,
    faces: Tensor,
    K: Tensor,
    colors: Sequence[tuple[int, int, int]],
    alpha: float = 0.75,
) -> np.ndarray:
    """Meshes (camera frame of this image) rendered shaded over ``image`` with their outlines."""
    height, width = image.shape[:2]
    out = image.astype(np.float32)
    if verts.shape[0] == 0:
        return image.copy()
    render = render_meshes(verts, faces, K, height, width)
    shade = _normal_shading(render.depth_map, K)
    instance = render.instance_map.cpu().numpy()
    table = np.array(list(colors) + [(0, 0, 0)], dtype=np.float32)  # index -1 picks the last row
    covered = instance >= 0
    shaded = table[instance] * shade[..., None]
    out[covered] = (1 - alpha) * out[covered] + alpha * shaded[covered]
    out = out.clip(0, 255).astype(np.uint8)
    for n, mask in enumerate(render.masks.cpu().numpy()):
        contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
        cv2.drawContours(out, contours, -1, colors[n], 1, cv2.LINE_AA)
    return out


def paint_masks(
    image: np.ndarray, masks: np.ndarray, colors: Sequence[tuple[int, int, int]], alpha: float = 0.6
) -> np.ndarray:
    """Masks (n, H, W) filled over a dimmed copy of ``image``."""
    out = image.astype(np.float32) * 0.5
    for mask, color in zip(masks, colors, strict=True):
        out[mask] = (1 - alpha) * out[mask] + alpha * np.asarray(color, np.float32)
    return out.clip(0, 255).astype(np.uint8)


def mask_pair(
    image: np.ndarray,
    true_masks: np.ndarray,
    true_colors: Sequence[tuple[int, int, int]],
    pred_masks: np.ndarray,
    pred_colors: Sequence[tuple[int, int, int]],
    title: str = "",
) -> np.ndarray:
    """[true masks | rendered prediction] side by side for one view."""
    left = label(paint_masks(image, true_masks, true_colors), f"{title} true".strip())
    right = label(paint_masks(image, pred_masks, pred_colors), "predicted")
    return np.concatenate([left, right], axis=1)


def birds_eye(
    pred_verts: Tensor,
    colors: Sequence[tuple[int, int, int]],
    true_verts: Sequence[Tensor] = (),
    cameras: Sequence[Tensor] = (),
    size: int = 512,
) -> np.ndarray:
    """Top-down (x right, z up the picture) plot in the input camera frame; ``cameras``: 4x4 cam -> input-cam poses."""
    footprints = [v[:, [0, 2]].detach().cpu().double().numpy() for v in pred_verts]
    outlines = [v[:, [0, 2]].detach().cpu().double().numpy() for v in true_verts]
    centres = [c[:3, 3][[0, 2]].cpu().double().numpy() for c in cameras]
    points = np.concatenate(footprints + outlines + [np.array(centres).reshape(-1, 2), np.zeros((1, 2))])
    lo, hi = points.min(0), points.max(0)
    span = float(max(hi - lo)) * 1.15 + 1e-6
    mid = 0.5 * (lo + hi)
    scale = size / span

    def pix(xz: np.ndarray) -> np.ndarray:
        x = (xz[..., 0] - mid[0]) * scale + size / 2
        y = size / 2 - (xz[..., 1] - mid[1]) * scale
        return np.stack([x, y], -1).round().astype(np.int32)

    canvas = np.full((size, size, 3), 30, np.uint8)
    step = 10 ** np.floor(np.log10(span / 2))
    for g in np.arange(np.floor((mid - span / 2) / step).min(), np.ceil((mid + span / 2) / step).max() + 1) * step:
        a, b = pix(np.array([[g, -1e3], [g, 1e3]])), pix(np.array([[-1e3, g], [1e3, g]]))
        cv2.line(canvas, tuple(a[0]), tuple(a[1]), (55, 55, 55), 1)
        cv2.line(canvas, tuple(b[0]), tuple(b[1]), (55, 55, 55), 1)
    layer = canvas.copy()
    for xz, color in zip(footprints, colors, strict=True):
        cv2.fillConvexPoly(layer, cv2.convexHull(pix(xz)), color, cv2.LINE_AA)
    canvas = cv2.addWeighted(layer, 0.7, canvas, 0.3, 0)
    for xz in outlines:
        cv2.polylines(canvas, [cv2.convexHull(pix(xz))], True, (255, 255, 255), 1, cv2.LINE_AA)
    for n, pose in enumerate(cameras):
        _draw_camera(canvas, pose.cpu().double().numpy(), pix, span / 12, (255, 220, 0) if n == 0 else (0, 200, 255))
    return label(canvas, f"top view, grid {step:g} m")


def _draw_camera(canvas: np.ndarray, pose: np.ndarray, pix, length: float, color: tuple[int, int, int]) -> None:
    """A wedge from the camera centre along its optical axis, in the x/z plane."""
    corners = np.array([[0, 0, 0], [-0.5, 0, 1], [0.5, 0, 1]]) * length
    world = corners @ pose[:3, :3].T + pose[:3, 3]
    cv2.polylines(canvas, [pix(world[:, [0, 2]])], True, color, 2, cv2.LINE_AA)


def legend(
    entries: Sequence[tuple[tuple[int, int, int] | None, str]], height: int = 320, title: str = ""
) -> np.ndarray:
    """A dark panel listing ``(colour, text)`` lines (colour None: plain text, no swatch)."""
    lines = ([(None, title)] if title else []) + list(entries)
    scale, step = 0.45, 20
    width = 24 + max([cv2.getTextSize(text, FONT, scale, 1)[0][0] for _, text in lines] + [200])
    canvas = np.full((max(height, step * len(lines) + 12), width, 3), 30, np.uint8)
    for n, (color, text) in enumerate(lines):
        y = 18 + n * step
        if color is not None:
            cv2.rectangle(canvas, (6, y - 11), (18, y + 1), color, -1)
        cv2.putText(canvas, text, (24 if color is not None else 6, y), FONT, scale, (235, 235, 235), 1, cv2.LINE_AA)
    return canvas


def label(image: np.ndarray, text: str) -> np.ndarray:
    out = image.copy()
    scale = max(0.4, min(out.shape[:2]) / 700)
    cv2.putText(out, text, (6, int(22 * scale / 0.5)), FONT, scale, (255, 255, 255), 1, cv2.LINE_AA)
    return out


def fit_height(image: np.ndarray, height: int) -> np.ndarray:
    h, w = image.shape[:2]
    return (
        image
        if h == height
        else cv2.resize(image, (max(1, round(w * height / h)), height), interpolation=cv2.INTER_AREA)
    )


def compose_rows(rows: Sequence[Sequence[np.ndarray]], height: int = 320, gap: int = 4) -> np.ndarray:
    """Panels scaled to one height, laid out in rows (left aligned, dark gaps)."""
    lines = []
    for panels in rows:
        scaled = [fit_height(p, height) for p in panels]
        pieces = []
        for p in scaled:
            pieces += [p, np.full((height, gap, 3), 15, np.uint8)]
        lines.append(np.concatenate(pieces[:-1], axis=1))
    width = max(line.shape[1] for line in lines)
    padded = [np.pad(line, ((0, gap), (0, width - line.shape[1]), (0, 0)), constant_values=15) for line in lines]
    return np.concatenate(padded, axis=0)


def write_png(path: str | Path, image: np.ndarray) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), cv2.cvtColor(image, cv2.COLOR_RGB2BGR)):
        raise UslError(f"{path}: OpenCV could not write the PNG")
    return path
