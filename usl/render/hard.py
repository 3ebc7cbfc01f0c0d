"""Z-buffer rasterizer for evaluation: visible instance masks and nearest depth per object.

Many objects in many views in one call: every mesh (an object placed in one view's
camera frame) belongs to one view, and each view has its own ``K``. A pixel is covered by
a face when its centre (docs/design.md §2: +0.5) lies inside the projected triangle, edges
included; the nearest face wins, with ties going to the lower face index. Depth is the
planar camera-frame z of the surface point seen through the pixel centre, interpolated
perspective-correctly for any projective ``K``. Faces with a vertex at or behind the near
plane are culled, not clipped. Sparse like the soft rasterizer: only pixels inside each
face's 2D box are visited, in chunks of bounded size; on the CPU in one compiled loop
(:mod:`usl.render.hard_cpu`, the same result bit for bit).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

import usl.render.face_tables as face_tables
import usl.render.hard_cpu as hard_cpu
from usl.render.screen import (
    DEFAULT_CHUNK_SIZE,
    DEFAULT_NEAR,
    FaceBoxes,
    ScreenFaces,
    check_packed_inputs,
    face_pixel_boxes,
    iter_face_pixels,
    perspective_depth,
    pixel_centres,
    project_faces,
    screen_barycentrics,
)

Tensor = torch.Tensor


@dataclass
class HardRender:
    """Result of :func:`rasterize_hard`; leading B is dropped when a single (3, 3) K was given.

    instance_map: (B, H, W) long mesh index of the nearest surface, -1 for background.
    depth_map: (B, H, W) planar depth of that surface, +inf for background.
    masks: (M, H, W) bool visible (occlusion-aware) mask of each mesh in its own view.
    nearest_depth: (M,) smallest depth over each mesh's visible pixels, NaN when it has none
        (the records' ``depth_min`` convention).
    """

    instance_map: Tensor
    depth_map: Tensor
    masks: Tensor
    nearest_depth: Tensor


@torch.no_grad()
def rasterize_hard(
    verts: Tensor,
    faces: Tensor,
    mesh_idx: Tensor,
    K: Tensor,
    height: int,
    width: int,
    mesh_view: Tensor | None = None,
    num_meshes: int | None = None,
    near: float = DEFAULT_NEAR,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
) -> HardRender:
    """Rasterize M meshes into B views of size (height, width) with a z-buffer.

    Args:
        verts: (V, 3) packed vertices, each in the camera frame of its mesh's view.
        faces: (F, 3) long indices into ``verts``.
        mesh_idx: (F,) long mesh index of each face, in [0, M).
        K: (3, 3) for a single view, or (B, 3, 3) for B views.
        mesh_view: (M,) long view of each mesh; required when K is (B, 3, 3).
        num_meshes: M; defaults to ``mesh_idx.max() + 1`` (or the length of ``mesh_view``).
        chunk_size: (face, pixel) pairs per chunk of the torch path (the compiled CPU loop takes
            one pair at a time).
    """
    single_view = K.dim() == 2
    if single_view:
        K = K.unsqueeze(0)
    check_packed_inputs(verts, faces, mesh_idx, K, "rasterize_hard")
    faces, mesh_idx = faces.long(), mesh_idx.long()
    if num_meshes is None:
        num_meshes = (
            mesh_view.numel() if mesh_view is not None else (int(mesh_idx.max()) + 1 if mesh_idx.numel() else 0)
        )
    if mesh_view is None:
        if K.shape[0] != 1:
            raise ValueError(
                f"rasterize_hard: K has {K.shape[0]} views, so mesh_view (M,) must say which view each mesh is in"
            )
        mesh_view = torch.zeros(num_meshes, dtype=torch.long, device=verts.device)
    mesh_view = mesh_view.long()
    if mesh_view.shape != (num_meshes,):
        raise ValueError(f"rasterize_hard: mesh_view must be ({num_meshes},), got {tuple(mesh_view.shape)}")

    num_views = K.shape[0]
    face_view = mesh_view[mesh_idx]
    screen = project_faces(verts, faces, face_view, K, near)
    boxes = face_pixel_boxes(screen, 0.0, height, width)
    if face_tables.available(screen.plane):
        zbuf, fbuf = hard_cpu.zbuffer(screen, boxes, face_view, num_views, height, width)
    else:
        zbuf, fbuf = _zbuffer(screen, boxes, face_view, num_views, height, width, chunk_size)

    # fbuf == -1 (background) picks the appended -1.
    instance = torch.cat([mesh_idx, mesh_idx.new_full((1,), -1)])[fbuf].view(num_views, height, width)
    depth_map = zbuf.view(num_views, height, width)
    ids = torch.arange(num_meshes, device=verts.device)
    masks = instance[mesh_view] == ids[:, None, None]
    covered = instance.reshape(-1) >= 0
    nearest = torch.full((num_meshes,), torch.inf, dtype=verts.dtype, device=verts.device)
    nearest = nearest.scatter_reduce_(0, instance.reshape(-1)[covered], zbuf[covered], "amin")
    nearest = torch.where(torch.isinf(nearest), torch.full_like(nearest, torch.nan), nearest)
    if single_view:
        instance, depth_map = instance[0], depth_map[0]
    return HardRender(instance_map=instance, depth_map=depth_map, masks=masks, nearest_depth=nearest)


def _zbuffer(
    screen: ScreenFaces, boxes: FaceBoxes, face_view: Tensor, num_views: int, height: int, width: int, chunk_size: int
) -> tuple[Tensor, Tensor]:
    """The torch path of :func:`usl.render.hard_cpu.zbuffer` (any device): per chunk of pairs, the
    smallest depth per pixel, then the lowest face index at that depth; a later chunk wins only
    with a strictly smaller depth."""
    num_pixels = num_views * height * width
    zbuf = torch.full((num_pixels,), torch.inf, dtype=screen.plane.dtype, device=screen.plane.device)
    fbuf = torch.full((num_pixels,), -1, dtype=torch.long, device=screen.plane.device)
    no_face = torch.iinfo(torch.long).max
    for face, col, row in iter_face_pixels(boxes, chunk_size):
        px, py = pixel_centres(col, row, screen.plane.dtype)
        bary = screen_barycentrics(px, py, screen.plane_of(face))
        inside = torch.nonzero((bary[0] >= 0) & (bary[1] >= 0) & (bary[2] >= 0)).squeeze(1)
        face = face.index_select(0, inside)
        view = face_view.index_select(0, face)
        pixel = (view * height + row.index_select(0, inside)) * width + col.index_select(0, inside)
        depth = perspective_depth(tuple(b.index_select(0, inside) for b in bary), screen.depths_of(face))
        chunk_z = torch.full_like(zbuf, torch.inf).scatter_reduce_(0, pixel, depth, "amin")
        winner = torch.nonzero(depth == chunk_z.index_select(0, pixel)).squeeze(1)
        chunk_f = torch.full_like(fbuf, no_face).scatter_reduce_(
            0, pixel.index_select(0, winner), face.index_select(0, winner), "amin"
        )
        closer = chunk_z < zbuf
        zbuf = torch.where(closer, chunk_z, zbuf)
        fbuf = torch.where(closer, chunk_f, fbuf)
    return zbuf, fbuf
