"""Differentiable soft silhouettes (SoftRas / PyTorch3D ``SoftSilhouetteShader`` semantics).

For a pixel and a face, ``d`` is the signed squared 2D distance from the pixel centre to
the projected triangle (negative inside), measured in normalised window units: the
window's *shorter* side spans [-1, 1], as in PyTorch3D's NDC, so ``sigma`` and
``blur_radius`` mean the same at any resolution (a square window spans [-1, 1] both
ways). Faces with ``d > blur_radius`` are ignored; of the rest, the ``faces_per_pixel``
nearest by depth are kept (all of them when it is None). Each kept face contributes
``p = sigmoid(-d / sigma)`` and the silhouette is ``1 - prod(1 - p)``, accumulated as a
sum of ``log sigmoid(d / sigma)`` for numerical stability.

Depth for that ordering is the perspective-correct planar depth at the pixel centre,
with barycentrics clamped to the triangle for pixels just outside it (PyTorch3D
extrapolates instead; the difference only matters for faces within the blur radius),
compared in float32 with ties going to the lower face index. Faces with a vertex at or
behind the near plane are culled, not clipped. As in PyTorch3D, the selection itself
(blur cut-off, nearest K) is not differentiated: the silhouette is piecewise smooth.

:func:`rasterize_soft` is sparse: it selects (face, pixel) pairs inside each face's 2D
box grown by the blur radius, without gradients, then recomputes ``d`` with gradients for
the kept pairs only. On CPU tensors (float32/float64) both steps are compiled loops
(:mod:`usl.render.soft_cpu`: the same pairs, an analytic backward); elsewhere, and without
numba, they are torch ops, chunk by chunk and checkpointed, so memory stays bounded by
``chunk_size``. :func:`rasterize_soft_dense` evaluates every (pixel, face) pair; it exists
as the reference for tests and the benchmark.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch.utils.checkpoint import checkpoint

import usl.render.face_tables as face_tables
import usl.render.soft_cpu as soft_cpu
from usl.render.screen import (
    DEFAULT_CHUNK_SIZE,
    DEFAULT_NEAR,
    Depths,
    Plane,
    ScreenFaces,
    blur_margin_pixels,
    check_packed_inputs,
    face_pixel_boxes,
    gather_rows,
    iter_face_pixels,
    ndc_scale,
    perspective_depth,
    pixel_centres,
    project_faces,
    signed_sq_distance,
)

Tensor = torch.Tensor


@dataclass(frozen=True)
class SoftRasterSettings:
    """Soft silhouette parameters (the paper: sigma = blur_radius = 1e-3, 10 faces per pixel).

    sigma, blur_radius: squared normalised-window distances (see module docstring).
    faces_per_pixel: keep the K nearest faces by depth per pixel; None keeps all faces
        within the blur radius.
    near: faces with a vertex whose homogeneous or planar depth is <= near are culled.
    chunk_size: (face, pixel) pairs examined at once by the torch path; bounds its working
        memory (the compiled CPU path holds a few bytes per candidate pair instead).
    """

    sigma: float = 1e-3
    blur_radius: float = 1e-3
    faces_per_pixel: int | None = 10
    near: float = DEFAULT_NEAR
    chunk_size: int = DEFAULT_CHUNK_SIZE

    def __post_init__(self) -> None:
        if self.sigma <= 0:
            raise ValueError(f"SoftRasterSettings: sigma must be > 0, got {self.sigma}")
        if self.blur_radius < 0:
            raise ValueError(f"SoftRasterSettings: blur_radius must be >= 0, got {self.blur_radius}")
        if self.faces_per_pixel is not None and self.faces_per_pixel < 1:
            raise ValueError(f"SoftRasterSettings: faces_per_pixel must be >= 1 or None, got {self.faces_per_pixel}")
        if self.chunk_size < 1:
            raise ValueError(f"SoftRasterSettings: chunk_size must be >= 1, got {self.chunk_size}")


def rasterize_soft(
    verts: Tensor,
    faces: Tensor,
    face_window: Tensor,
    K: Tensor,
    height: int,
    width: int,
    settings: SoftRasterSettings = SoftRasterSettings(),
) -> Tensor:
    """Soft silhouettes of P windows in one call, differentiable w.r.t. ``verts`` (and ``K``).

    Args:
        verts: (V, 3) packed camera-frame vertices (OpenCV axes).
        faces: (F, 3) long indices into ``verts``.
        face_window: (F,) long: the window each face is drawn into (e.g. the mesh index
            ``Meshes.faces_packed_to_mesh_idx()`` when mesh p is rendered into window p).
        K: (P, 3, 3) per-window intrinsics mapping camera points to that window's pixels.
        height, width: window size in pixels (shared by all windows).
    Returns:
        (P, height, width) silhouettes in [0, 1].
    """
    check_packed_inputs(verts, faces, face_window, K, "rasterize_soft")
    faces, face_window = faces.long(), face_window.long()
    num_windows = K.shape[0]
    if num_windows * height * width >= 1 << 31:  # flat pixel indices must fit the sort key
        raise ValueError(
            f"rasterize_soft: {num_windows} windows of {height}x{width} exceed 2**31 pixels; split the batch"
        )
    screen = project_faces(verts, faces, face_window, K, settings.near)
    scale = ndc_scale(height, width) ** 2 / settings.sigma
    num_pixels = num_windows * height * width
    if face_tables.available(screen.plane):
        pairs = soft_cpu.select_pairs(screen, face_window, num_windows, height, width, settings)
        log_transparency = soft_cpu.LogTransparency.apply(screen.plane, pairs, num_pixels, scale)
    else:
        log_transparency = _torch_log_transparency(screen, face_window, num_pixels, height, width, scale, settings)
    return (-torch.expm1(log_transparency)).view(num_windows, height, width)


def _torch_log_transparency(
    screen: ScreenFaces,
    face_window: Tensor,
    num_pixels: int,
    height: int,
    width: int,
    scale: float,
    settings: SoftRasterSettings,
) -> Tensor:
    """(num_pixels,) sums of log(1 - p) per flat pixel, as torch ops (any device)."""
    face, pixel = _select_pairs(screen, face_window, height, width, settings)
    log_transparency = screen.plane.new_zeros(num_pixels)
    # With gradients and more than one chunk, each chunk is checkpointed: backward recomputes
    # it, so autograd memory stays bounded by chunk_size pairs instead of growing with the batch.
    checkpointed = torch.is_grad_enabled() and screen.plane.requires_grad and face.numel() > settings.chunk_size
    # At least one (possibly empty) chunk, so a blank render stays attached to the graph.
    for start in range(0, max(face.numel(), 1), settings.chunk_size):
        args = (
            screen.plane,
            face[start : start + settings.chunk_size],
            pixel[start : start + settings.chunk_size],
            height,
            width,
            scale,
        )
        terms = (
            checkpoint(_log_transparency_terms, *args, use_reentrant=False)
            if checkpointed
            else _log_transparency_terms(*args)
        )
        log_transparency = log_transparency.index_add(0, args[2], terms)
    return log_transparency


def _log_transparency_terms(
    plane: Tensor, face: Tensor, pixel: Tensor, height: int, width: int, scale: float
) -> Tensor:
    """log(1 - p) = log sigmoid(d / sigma) for each (face, flat pixel) pair; ``plane`` is
    the (16, F) table of :class:`Plane` rows."""
    px, py = pixel_centres(pixel % width, (pixel // width) % height, plane.dtype)
    dist, _ = signed_sq_distance(px, py, Plane(*gather_rows(plane, face)))
    return F.logsigmoid(dist * scale)


@torch.no_grad()
def _select_pairs(
    screen: ScreenFaces, face_window: Tensor, height: int, width: int, settings: SoftRasterSettings
) -> tuple[Tensor, Tensor]:
    """(face, flat pixel) pairs within the blur radius, capped to the nearest K per pixel.

    The flat pixel index is ``window * H * W + row * W + col``.
    """
    scale2 = ndc_scale(height, width) ** 2
    boxes = face_pixel_boxes(screen, blur_margin_pixels(settings.blur_radius, height, width), height, width)
    dtype = screen.plane.dtype
    faces_kept, pixels_kept, depths_kept = [], [], []
    for face, col, row in iter_face_pixels(boxes, settings.chunk_size):
        px, py = pixel_centres(col, row, dtype)
        dist, bary = signed_sq_distance(px, py, screen.plane_of(face))
        near_enough = torch.nonzero(dist * scale2 <= settings.blur_radius).squeeze(1)
        face = face.index_select(0, near_enough)
        faces_kept.append(face)
        window = face_window.index_select(0, face)
        pixels_kept.append(
            (window * height + row.index_select(0, near_enough)) * width + col.index_select(0, near_enough)
        )
        if settings.faces_per_pixel is not None:
            bary = tuple(b.index_select(0, near_enough) for b in bary)
            depths_kept.append(perspective_depth(bary, screen.depths_of(face), clip=True))
    if not faces_kept:
        empty = face_window.new_zeros(0)
        return empty, empty
    face, pixel = torch.cat(faces_kept), torch.cat(pixels_kept)
    if settings.faces_per_pixel is not None:
        keep = nearest_per_pixel(pixel, torch.cat(depths_kept), settings.faces_per_pixel)
        kept = torch.nonzero(keep).squeeze(1)
        face, pixel = face.index_select(0, kept), pixel.index_select(0, kept)
    return face, pixel


def nearest_per_pixel(pixel: Tensor, depth: Tensor, k: int) -> Tensor:
    """Bool mask of the pairs that rank among the ``k`` smallest depths of their pixel.

    Depth is compared in float32 and ties go to the earlier pair (the lower face index, in
    the order pairs are enumerated). All pairs are ranked by one stable sort on the key
    ``pixel << 32 | float32 bits of depth`` (the bit pattern of a positive float orders like
    its value), a pair's rank being its distance from the start of its pixel's run. Sorting
    every pair, not only those of pixels with more than ``k``, keeps every size known on the
    host: nothing is read from the device.
    """
    depth_bits = _ordering_depth(depth).view(torch.int32).long()
    order = torch.argsort((pixel << 32) | depth_bits, stable=True)
    sorted_pixel = pixel.index_select(0, order)
    position = torch.arange(order.numel(), device=pixel.device)
    run_start = torch.ones_like(sorted_pixel, dtype=torch.bool)
    run_start[1:] = sorted_pixel[1:] != sorted_pixel[:-1]
    first = torch.cummax(torch.where(run_start, position, torch.zeros_like(position)), dim=0).values
    return torch.empty_like(run_start).index_copy_(0, order, position - first < k)


def _ordering_depth(depth: Tensor) -> Tensor:
    """The depth the nearest-K selection compares (float32, so it packs into a sort key)."""
    return depth.float()


def rasterize_soft_dense(
    verts: Tensor,
    faces: Tensor,
    face_window: Tensor,
    K: Tensor,
    height: int,
    width: int,
    settings: SoftRasterSettings = SoftRasterSettings(),
) -> Tensor:
    """Reference for :func:`rasterize_soft`: evaluates every (pixel, face) pair densely.

    Same arguments and result; memory and time grow as P * H * W * F. ``chunk_size`` is
    ignored. For tests and benchmarks only.
    """
    check_packed_inputs(verts, faces, face_window, K, "rasterize_soft_dense")
    faces, face_window = faces.long(), face_window.long()
    num_windows = K.shape[0]
    screen = project_faces(verts, faces, face_window, K, settings.near)
    scale2 = ndc_scale(height, width) ** 2
    rows, cols = torch.meshgrid(
        torch.arange(height, device=verts.device), torch.arange(width, device=verts.device), indexing="ij"
    )
    px, py = pixel_centres(cols.reshape(-1, 1), rows.reshape(-1, 1), verts.dtype)  # (H*W, 1)
    silhouettes = []
    for window in range(num_windows):
        in_window = torch.nonzero(screen.visible & (face_window == window)).squeeze(1)
        dist, bary = signed_sq_distance(px, py, screen.plane_of(in_window))  # (H*W, Fw)
        dist = dist * scale2
        candidate = dist.detach() <= settings.blur_radius
        if settings.faces_per_pixel is not None and in_window.numel() > 0:
            depth = perspective_depth(
                tuple(b.detach() for b in bary), Depths(*(d.detach() for d in screen.depths_of(in_window))), clip=True
            )
            depth = torch.where(candidate, _ordering_depth(depth), torch.inf)
            candidate = candidate & _nearest_dense(depth, settings.faces_per_pixel)
        log_t = torch.where(candidate, F.logsigmoid(dist / settings.sigma), torch.zeros_like(dist))
        silhouettes.append(-torch.expm1(log_t.sum(1)).view(height, width))
    return torch.stack(silhouettes) if silhouettes else verts.new_zeros(0, height, width)


def _nearest_dense(depth: Tensor, k: int) -> Tensor:
    """(N, F) bool: the k smallest depths of each row, ties going to the lower face index
    (the order :func:`nearest_per_pixel` keeps), at the cost of one ``topk``."""
    k = min(k, depth.shape[1])
    kth = torch.topk(depth, k, dim=1, largest=False).values[:, -1:]
    below = depth < kth
    tied = depth == kth
    room = k - below.sum(dim=1, keepdim=True)
    return below | (tied & (torch.cumsum(tied, dim=1) <= room))
