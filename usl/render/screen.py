"""Screen-space building blocks shared by the soft and hard rasterizers.

Faces are projected per *window*: every face carries the index of the window (an
(object, view) crop, or a whole view) it is drawn into, and each window has its own
3x3 ``K`` mapping camera coordinates to that window's pixel frame (docs/design.md §2: pixel
centres at +0.5, general ``K`` with a homogeneous divide, via ``usl.geometry.cameras``).

Sparsity comes from :func:`iter_face_pixels`: it walks only the (face, pixel) pairs
whose pixel centre lies inside the face's 2D box (grown by a margin), in chunks of a
bounded number of pairs, with no Python loop over faces or pixels.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import NamedTuple

import torch

from usl.geometry.cameras import project

Tensor = torch.Tensor

# Faces with any vertex whose homogeneous depth w (or planar depth z) is at or below this
# are culled: we do not clip triangles against the near plane.
DEFAULT_NEAR = 1e-3
# Default number of (face, pixel) pairs examined at once: the ~3M candidate pairs of a
# Hypersim-shaped batch (2 images x 20 objects x 5 views, 72x72 windows) fit one chunk, so the
# torch path (CUDA's) runs a fixed number of ops up to that size. Working memory is about 180
# bytes per pair in float32 (selection and gradient terms together: ~720 MiB peak for 4M pairs
# in one chunk, ~370 MiB in chunks of 1M).
DEFAULT_CHUNK_SIZE = 1 << 22
# Twice-signed screen areas (pixels^2) at or below this mark degenerate faces, which are culled.
_MIN_AREA = 1e-9


class Plane(NamedTuple):
    """2D data of faces (or of the face of each pair) as separate contiguous tensors that
    broadcast together: corner k at (xk, yk); edge k runs from corner k+1 to corner k+2
    (the edge opposite corner k) with vector (exk, eyk) and inverse squared length ilk;
    inv_area is 1 / (twice the signed area)."""

    x0: Tensor
    y0: Tensor
    x1: Tensor
    y1: Tensor
    x2: Tensor
    y2: Tensor
    ex0: Tensor
    ey0: Tensor
    ex1: Tensor
    ey1: Tensor
    ex2: Tensor
    ey2: Tensor
    il0: Tensor
    il1: Tensor
    il2: Tensor
    inv_area: Tensor

    def edges(self) -> tuple[tuple[Tensor, Tensor, Tensor, Tensor, Tensor], ...]:
        """(start x, start y, vector x, vector y, inverse squared length) of edges 0, 1, 2."""
        return (
            (self.x1, self.y1, self.ex0, self.ey0, self.il0),
            (self.x2, self.y2, self.ex1, self.ey1, self.il1),
            (self.x0, self.y0, self.ex2, self.ey2, self.il2),
        )


class Depths(NamedTuple):
    """Homogeneous depth w (the divisor of ``K @ X``) and planar depth z of corners 0, 1, 2."""

    w0: Tensor
    w1: Tensor
    w2: Tensor
    z0: Tensor
    z1: Tensor
    z2: Tensor


@dataclass
class ScreenFaces:
    """Faces projected into their windows.

    xy: (F, 3, 2) pixel coordinates in the face's window; plane: (16, F) and depths: (6, F),
    the rows of :class:`Plane` and :class:`Depths` (structure of arrays, so per-pair
    gathers stay contiguous); visible: (F,) bool, False for culled faces (behind the near
    plane, degenerate, or non-finite).
    """

    xy: Tensor
    plane: Tensor
    depths: Tensor
    visible: Tensor

    def plane_of(self, face: Tensor) -> Plane:
        """2D data of the faces ``face`` (any long index tensor of shape (N,))."""
        return Plane(*gather_rows(self.plane, face))

    def depths_of(self, face: Tensor) -> Depths:
        return Depths(*gather_rows(self.depths, face))


def gather_rows(table: Tensor, index: Tensor) -> list[Tensor]:
    """``table[:, index]`` as a list of rows; one 1-D ``index_select`` per row is much
    faster on the CPU than gathering columns."""
    return [row.index_select(0, index) for row in table]


def project_faces(
    verts: Tensor, faces: Tensor, face_window: Tensor, K: Tensor, near: float = DEFAULT_NEAR
) -> ScreenFaces:
    """Project packed faces with their window's ``K``, precompute per-face 2D data, and
    mark the faces to cull. Differentiable w.r.t. ``verts`` and ``K``.

    Args:
        verts: (V, 3) camera-frame vertices (OpenCV axes).
        faces: (F, 3) long indices into ``verts``.
        face_window: (F,) long window index of each face, in [0, P).
        K: (P, 3, 3) per-window intrinsics mapping camera points to window pixels.
    """
    points = verts[faces]  # (F, 3, 3)
    xy, w = project(points, K.to(verts.dtype)[face_window])
    z = points[..., 2]
    x, y = xy[..., 0], xy[..., 1]
    ex = x.roll(-2, dims=1) - x.roll(-1, dims=1)  # edge k: corner k+1 -> corner k+2
    ey = y.roll(-2, dims=1) - y.roll(-1, dims=1)
    inv_len2 = 1.0 / (ex * ex + ey * ey).clamp_min(torch.finfo(xy.dtype).tiny)
    twice_area = ex[:, 2] * (-ey[:, 1]) - ey[:, 2] * (-ex[:, 1])  # (p1 - p0) x (p2 - p0)
    inv_area = 1.0 / torch.where(twice_area == 0, torch.ones_like(twice_area), twice_area)
    corners = torch.stack([x, y], dim=2).reshape(-1, 6)
    edges = torch.stack([ex, ey], dim=2).reshape(-1, 6)
    plane = torch.cat([corners, edges, inv_len2, inv_area[:, None]], dim=1).t().contiguous()
    visible = (
        (w > near).all(-1) & (z > near).all(-1) & torch.isfinite(xy).all(-1).all(-1) & (twice_area.abs() > _MIN_AREA)
    )
    return ScreenFaces(xy=xy, plane=plane, depths=torch.cat([w, z], dim=1).t().contiguous(), visible=visible)


@dataclass
class FaceBoxes:
    """Integer pixel ranges per face: columns [x0, x0 + nx), rows [y0, y0 + ny)."""

    x0: Tensor
    y0: Tensor
    nx: Tensor
    ny: Tensor


def face_pixel_boxes(screen: ScreenFaces, margin: float, height: int, width: int) -> FaceBoxes:
    """Pixels whose centre lies in each visible face's box grown by ``margin`` pixels.

    Culled faces get an empty range. Coordinates are clamped before the integer cast so
    huge projections (faces grazing the near plane) cannot overflow.
    """
    xy = torch.nan_to_num(screen.xy.detach(), nan=0.0, posinf=1e9, neginf=-1e9)
    lo = xy.amin(dim=1) - margin
    hi = xy.amax(dim=1) + margin
    # Pixel i has its centre at i + 0.5: the first index with centre >= lo is ceil(lo - 0.5).
    col_lo = torch.ceil(lo[:, 0].clamp(-1.0, width + 1.0) - 0.5).long().clamp(0, width)
    col_hi = torch.floor(hi[:, 0].clamp(-1.0, width + 1.0) - 0.5).long().clamp(-1, width - 1)
    row_lo = torch.ceil(lo[:, 1].clamp(-1.0, height + 1.0) - 0.5).long().clamp(0, height)
    row_hi = torch.floor(hi[:, 1].clamp(-1.0, height + 1.0) - 0.5).long().clamp(-1, height - 1)
    keep = screen.visible
    nx = torch.where(keep, (col_hi - col_lo + 1).clamp_min(0), torch.zeros_like(col_lo))
    ny = torch.where(keep, (row_hi - row_lo + 1).clamp_min(0), torch.zeros_like(row_lo))
    return FaceBoxes(x0=col_lo, y0=row_lo, nx=nx, ny=ny)


def iter_face_pixels(boxes: FaceBoxes, chunk_size: int = DEFAULT_CHUNK_SIZE) -> Iterator[tuple[Tensor, Tensor, Tensor]]:
    """Yield ``(face, col, row)`` long tensors enumerating every (face, pixel) pair in the boxes.

    Pairs are numbered consecutively face after face (so ``face`` is non-decreasing); each
    chunk is a contiguous range of at most ``chunk_size`` pair numbers, so a single huge
    face is split across chunks like any other range.
    """
    counts = boxes.nx * boxes.ny
    ends = torch.cumsum(counts, 0)
    starts = ends - counts
    total = int(ends[-1]) if ends.numel() else 0  # the one device read: how many pairs
    every_face = torch.arange(counts.numel(), device=ends.device)
    for start in range(0, total, chunk_size):
        stop = min(start + chunk_size, total)
        # each face's share of pairs start .. stop - 1 (0 outside): no read of which faces those are
        repeats = (ends.clamp_max(stop) - starts.clamp_min(start)).clamp_min(0)
        face = torch.repeat_interleave(every_face, repeats, output_size=stop - start)
        local = torch.arange(start, stop, device=ends.device) - starts.index_select(0, face)
        nx = boxes.nx.index_select(0, face)
        yield face, boxes.x0.index_select(0, face) + local % nx, boxes.y0.index_select(0, face) + local // nx


def pixel_centres(col: Tensor, row: Tensor, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """Continuous coordinates of pixel centres (docs/design.md §2: +0.5)."""
    return col.to(dtype) + 0.5, row.to(dtype) + 0.5


def signed_sq_distance(px: Tensor, py: Tensor, f: Plane) -> tuple[Tensor, tuple[Tensor, Tensor, Tensor]]:
    """Signed squared distance from points to triangles, and screen barycentrics.

    ``px``, ``py`` broadcast against the :class:`Plane` fields. The distance is to the
    nearest point of the triangle's boundary (the closest of its three segments), negative
    when the point is inside (all barycentrics >= 0), in the units of the inputs squared.
    Works for either winding. Returns (dist, (b0, b1, b2)); the barycentrics sum to 1 and
    are affine in screen space.
    """
    bary, dists = [], []
    for ax, ay, ex, ey, inv_len2 in f.edges():
        rx, ry = px - ax, py - ay
        bary.append((ex * ry - ey * rx) * f.inv_area)
        t = ((rx * ex + ry * ey) * inv_len2).clamp(0.0, 1.0)
        ox, oy = rx - t * ex, ry - t * ey
        dists.append(ox * ox + oy * oy)
    inside = (bary[0] >= 0) & (bary[1] >= 0) & (bary[2] >= 0)
    dist = torch.minimum(torch.minimum(dists[0], dists[1]), dists[2])
    return torch.where(inside, -dist, dist), (bary[0], bary[1], bary[2])


def screen_barycentrics(px: Tensor, py: Tensor, f: Plane) -> tuple[Tensor, Tensor, Tensor]:
    """Barycentrics (b0, b1, b2) of points w.r.t. triangles; all >= 0 inside, either winding."""
    b0, b1, b2 = (((ex * (py - ay) - ey * (px - ax)) * f.inv_area) for ax, ay, ex, ey, _ in f.edges())
    return b0, b1, b2


def perspective_depth(bary: tuple[Tensor, Tensor, Tensor], d: Depths, clip: bool = False) -> Tensor:
    """Planar depth of the surface point seen through a pixel, interpolated perspective-correctly.

    Screen barycentrics ``b`` turn into 3D ones as ``b_i / w_i`` renormalised, where
    ``w_i`` is the homogeneous divisor of vertex i; this holds for any projective ``K``
    (tilt-shift included), not only for w = z. With ``clip`` the barycentrics are first
    clamped to the triangle, giving the depth of the nearest triangle point for pixels
    outside it (used to order faces within the blur radius).
    """
    b0, b1, b2 = bary
    if clip:
        b0, b1, b2 = b0.clamp_min(0.0), b1.clamp_min(0.0), b2.clamp_min(0.0)
    q0, q1, q2 = b0 / d.w0, b1 / d.w1, b2 / d.w2
    return (q0 * d.z0 + q1 * d.z1 + q2 * d.z2) / (q0 + q1 + q2)


def ndc_scale(height: int, width: int) -> float:
    """Normalised units per pixel: the window's shorter side spans [-1, 1] (PyTorch3D's NDC)."""
    return 2.0 / min(height, width)


def blur_margin_pixels(blur_radius: float, height: int, width: int) -> float:
    """The blur radius (a squared NDC distance) as a distance in pixels."""
    return math.sqrt(max(blur_radius, 0.0)) / ndc_scale(height, width)


def check_packed_inputs(verts: Tensor, faces: Tensor, face_window: Tensor, K: Tensor, where: str) -> None:
    """Clear errors for malformed packed meshes (``where`` names the caller)."""
    if verts.dim() != 2 or verts.shape[-1] != 3 or not verts.is_floating_point():
        raise ValueError(f"{where}: verts must be a float (V, 3) tensor, got {verts.dtype} {tuple(verts.shape)}")
    if faces.dim() != 2 or faces.shape[-1] != 3:
        raise ValueError(f"{where}: faces must be (F, 3), got {tuple(faces.shape)}")
    if face_window.shape != faces.shape[:1]:
        raise ValueError(
            f"{where}: the per-face index must be (F,) = ({faces.shape[0]},), got {tuple(face_window.shape)}"
        )
    if K.dim() != 3 or K.shape[-2:] != (3, 3):
        raise ValueError(f"{where}: K must be (P, 3, 3), got {tuple(K.shape)}")
