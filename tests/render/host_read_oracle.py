"""The soft rasterizer's former pair enumeration and nearest-K selection, kept as test oracles for
the versions that read nothing from the device: these read which faces each chunk spans
(``tolist``) and which pixels are crowded (``bincount``, ``nonzero``)."""

from __future__ import annotations

from collections.abc import Iterator

import torch

from usl.render.screen import FaceBoxes
from usl.render.soft import _ordering_depth

Tensor = torch.Tensor


def iter_face_pixels_by_span(boxes: FaceBoxes, chunk_size: int) -> Iterator[tuple[Tensor, Tensor, Tensor]]:
    """``iter_face_pixels`` reading each chunk's first and last face from the device."""
    counts = boxes.nx * boxes.ny
    ends = torch.cumsum(counts, 0)
    starts = ends - counts
    total = int(ends[-1]) if ends.numel() else 0
    for start in range(0, total, chunk_size):
        stop = min(start + chunk_size, total)
        bounds = torch.searchsorted(ends, torch.tensor([start, stop - 1], device=ends.device), right=True).tolist()
        span = slice(bounds[0], bounds[1] + 1)
        repeats = ends[span].clamp_max(stop) - starts[span].clamp_min(start)
        face = torch.repeat_interleave(
            torch.arange(span.start, span.stop, device=ends.device), repeats, output_size=stop - start
        )
        local = torch.arange(start, stop, device=ends.device) - starts.index_select(0, face)
        nx = boxes.nx.index_select(0, face)
        yield face, boxes.x0.index_select(0, face) + local % nx, boxes.y0.index_select(0, face) + local // nx


def nearest_per_pixel_of_crowded(pixel: Tensor, depth: Tensor, k: int) -> Tensor:
    """``nearest_per_pixel`` sorting only the pairs of pixels with more than ``k``."""
    counts = torch.bincount(pixel)
    keep = counts.index_select(0, pixel) <= k
    crowded = torch.nonzero(~keep).squeeze(1)
    depth_bits = _ordering_depth(depth.index_select(0, crowded)).view(torch.int32).long()
    key = (pixel.index_select(0, crowded) << 32) | depth_bits
    order = crowded.index_select(0, torch.argsort(key, stable=True))
    sorted_pixel = pixel.index_select(0, order)
    position = torch.arange(order.numel(), device=pixel.device)
    run_start = torch.ones_like(sorted_pixel, dtype=torch.bool)
    run_start[1:] = sorted_pixel[1:] != sorted_pixel[:-1]
    first = torch.cummax(torch.where(run_start, position, torch.zeros_like(position)), dim=0).values
    keep[order.index_select(0, torch.nonzero(position - first < k).squeeze(1))] = True
    return keep
