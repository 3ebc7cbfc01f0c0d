"""Projected faces as the host arrays the rasterizers' compiled CPU loops read.

:mod:`usl.render.soft_cpu` and :mod:`usl.render.hard_cpu` walk the same per-face data: one row per
face of the 16 :class:`~usl.render.screen.Plane` fields then the 6 :class:`~usl.render.screen.Depths`
fields (row-major, so a face's data is one cache line or two), its window and pixel box as integers,
and the pixel-centre coordinates computed with :func:`usl.render.screen.pixel_centres`' arithmetic.
"""

from __future__ import annotations

import numpy as np
import torch

from usl.render.screen import FaceBoxes, ScreenFaces
from usl.utils.compiled import compiled, serves

Tensor = torch.Tensor
NUMPY_DTYPES = {torch.float32: np.float32, torch.float64: np.float64}


def available(table: Tensor) -> bool:
    """Whether the compiled loops serve faces held in ``table`` (a CPU float32/float64 tensor)."""
    return serves(table) and table.dtype in NUMPY_DTYPES


def face_table(screen: ScreenFaces) -> np.ndarray:
    """(F, 22) plane then depth fields per face, in the faces' dtype (columns: corners x0 y0 x1 y1
    x2 y2, edge vectors ex0 ey0 ex1 ey1 ex2 ey2, inverse squared edge lengths, 1 / twice the signed
    area, then w0 w1 w2 z0 z1 z2)."""
    return np.ascontiguousarray(torch.cat([screen.plane.detach(), screen.depths.detach()]).numpy().T)


def box_table(face_window: Tensor, boxes: FaceBoxes) -> np.ndarray:
    """(F, 5) int64 window, first column, first row, columns and rows of each face's pixel box."""
    return np.ascontiguousarray(torch.stack([face_window, boxes.x0, boxes.y0, boxes.nx, boxes.ny]).numpy().T)


def centres(size: int, dtype: np.dtype) -> np.ndarray:
    """Pixel-centre coordinates 0.5, 1.5, ... of ``size`` pixels with ``pixel_centres``' arithmetic
    (``col.to(dtype) + 0.5``)."""
    return np.arange(size).astype(dtype) + dtype(0.5)


@compiled
def face_row(c):  # pragma: no cover
    """A :func:`face_table` row as its 22 fields, in column order (for the compiled loops)."""
    return (
        c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7], c[8], c[9], c[10],
        c[11], c[12], c[13], c[14], c[15], c[16], c[17], c[18], c[19], c[20], c[21],
    )  # fmt: skip
