"""Metres per unit of a capture's poses, and where that number comes from (written to the manifest).

In order: ``--scale`` when given; 1 for ``transforms.json`` (capture apps write metres); for COLMAP
and SfM models, the depth maps when the capture has them: the median over all sparse points a frame
sees of (depth map at the point's pixel) / (the point's depth in the model); else a prior: the
median depth of the sparse points is ``PRIOR_MEDIAN_DEPTH`` metres (a hand-held capture of a room,
objects a couple of metres away), good to a factor of about two, which the layout ranges absorb
but metric evaluation does not.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from usl.errors import UslError

from .posed import PosedCapture

PRIOR_MEDIAN_DEPTH = 2.0  # metres


@dataclass(frozen=True)
class Scale:
    metres_per_unit: float
    origin: str
    samples: int = 0  # sparse points the depth estimate used
    spread: float | None = None  # their ratios' median absolute deviation, relative to the median

    def describe(self) -> dict[str, object]:
        about: dict[str, object] = {"scale": self.metres_per_unit, "scale_origin": self.origin}
        if self.samples:
            about.update(scale_samples=self.samples, scale_spread=self.spread)
        return about


def depth_ratios(
    posed: PosedCapture, raw_depth: Callable[[int], np.ndarray | None], color_size: tuple[int, int]
) -> np.ndarray:
    """depth map / model depth at every sparse point with a valid depth pixel, all frames."""
    assert posed.points is not None
    width, height = color_size
    ratios = []
    for index, uv in posed.points.uv.items():
        depth = raw_depth(index)
        if depth is None:
            continue
        dh, dw = depth.shape
        col = np.floor(uv[:, 0] * dw / width).astype(np.int64)
        row = np.floor(uv[:, 1] * dh / height).astype(np.int64)
        z = posed.points.z[index]
        inside = (col >= 0) & (col < dw) & (row >= 0) & (row < dh) & (z > 0)
        metres = depth[row[inside], col[inside]]
        good = np.isfinite(metres) & (metres > 0)
        ratios.append(metres[good] / z[inside][good])
    return np.concatenate(ratios) if ratios else np.zeros(0)


def metric_scale(
    posed: PosedCapture,
    given: float | None,
    raw_depth: Callable[[int], np.ndarray | None],
    color_size: tuple[int, int],
    where: str,
) -> Scale:
    if given is not None:
        return Scale(given, "--scale")
    if posed.metric:
        return Scale(1.0, f"{posed.pose_source} poses taken as metres (capture apps write metres)")
    if posed.points is None or not posed.points.z:
        raise UslError(f"{where}: {posed.pose_source} has no sparse points to fix the metric scale; pass --scale")
    if any(f.depth is not None for f in posed.frames):
        ratios = depth_ratios(posed, raw_depth, color_size)
        if ratios.size < 10:
            raise UslError(f"{where}: only {ratios.size} sparse points fall on valid depth; pass --scale")
        median = float(np.median(ratios))
        spread = float(np.median(np.abs(ratios - median)) / median)
        return Scale(median, "depth maps: median of depth / SfM point depth", int(ratios.size), spread)
    z = np.concatenate(list(posed.points.z.values()))
    median_z = float(np.median(z[z > 0]))
    return Scale(PRIOR_MEDIAN_DEPTH / median_z, f"prior: median SfM point depth = {PRIOR_MEDIAN_DEPTH} m")
