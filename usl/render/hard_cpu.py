"""The z-buffer rasterizer's CPU path: the depth test of every (face, pixel) pair as one compiled loop.

As torch ops, :func:`usl.render.hard.rasterize_hard` spends its time on a dozen elementwise ops and
two scatters per candidate pair, chunk after chunk; usl-eval renders every object into every view
of every input view, so this is a large share of its time. Here the same pairs (each face's pixel
box from :func:`usl.render.screen.face_pixel_boxes`) are visited face after face in one loop
compiled by numba (:mod:`usl.utils.compiled`), with the torch path's arithmetic op for op in the
faces' dtype: the same screen barycentrics, inside test (edges included) and perspective-correct
depth, and a pixel keeps the first face with the smallest depth, so ties go to the lower face index
as the torch path's ``amin`` over face indices does. The torch path stays for CUDA and is the
tests' oracle.
"""

from __future__ import annotations

import numpy as np
import torch

from usl.render.face_tables import NUMPY_DTYPES, box_table, centres, face_row, face_table
from usl.render.screen import FaceBoxes, ScreenFaces
from usl.utils.compiled import compiled

Tensor = torch.Tensor


def zbuffer(
    screen: ScreenFaces, boxes: FaceBoxes, face_view: Tensor, num_views: int, height: int, width: int
) -> tuple[Tensor, Tensor]:
    """(B * H * W,) nearest depth (+inf for background) and (B * H * W,) long index of the face
    seen there (-1 for background), for faces projected into B views."""
    np_dtype = NUMPY_DTYPES[screen.plane.dtype]
    zbuf = np.full(num_views * height * width, np.inf, dtype=np_dtype)
    fbuf = np.full(num_views * height * width, -1, dtype=np.int64)
    _zbuffer_loop(
        face_table(screen),
        box_table(face_view, boxes),
        centres(max(height, width), np_dtype),
        height,
        width,
        zbuf,
        fbuf,
    )
    return torch.from_numpy(zbuf), torch.from_numpy(fbuf)


# Face table columns: see usl.render.face_tables.face_table; edge k runs from corner k + 1.
@compiled
def _zbuffer_loop(faces, ints, centres, height, width, zbuf, fbuf):  # pragma: no cover
    """Every pair of each face's box, row-major, face after face: the pixel centre is inside when
    its three barycentrics (``usl.render.screen.screen_barycentrics``, op for op) are >= 0; its
    depth (``perspective_depth``, op for op) replaces the pixel's when strictly smaller, so the
    lower face index keeps a tie. A NaN depth (only from overflowing coordinates) never wins."""
    for f in range(faces.shape[0]):
        nx, ny = ints[f, 3], ints[f, 4]
        if nx == 0 or ny == 0:
            continue
        x0, y0, x1, y1, x2, y2, ex0, ey0, ex1, ey1, ex2, ey2, _, _, _, inv_area, w0, w1, w2, z0, z1, z2 = face_row(
            faces[f]
        )
        base, col0, row0 = ints[f, 0] * height, ints[f, 1], ints[f, 2]
        for r in range(row0, row0 + ny):
            py = centres[r]
            p = (base + r) * width + col0
            for j in range(nx):
                px = centres[col0 + j]
                b0 = (ex0 * (py - y1) - ey0 * (px - x1)) * inv_area
                b1 = (ex1 * (py - y2) - ey1 * (px - x2)) * inv_area
                b2 = (ex2 * (py - y0) - ey2 * (px - x0)) * inv_area
                if b0 >= 0 and b1 >= 0 and b2 >= 0:
                    q0, q1, q2 = b0 / w0, b1 / w1, b2 / w2
                    depth = (q0 * z0 + q1 * z1 + q2 * z2) / (q0 + q1 + q2)
                    if depth < zbuf[p + j]:
                        zbuf[p + j] = depth
                        fbuf[p + j] = f
