"""Warping a track's last mask into the current frame with depth and the relative camera pose.

With a large frame stride an object moves far between processed frames, and comparing masks in
place fails. Backward warping fixes that: every current pixel with depth is lifted to 3D, moved
into the earlier camera and looked up in the earlier mask. A lookup only counts where the earlier
frame's own depth agrees with the moved point (within ``tolerance`` metres), i.e. where the point
was visible there too. Pixels without a usable correspondence are reported as not covered, so
the tracker compares masks only where the warp is defined. Matching needs no fine detail, so the
warp runs on a grid of at most ``max_side`` pixels a side (masks are resampled to it and back).
"""

from __future__ import annotations

import numpy as np
import torch
from pycocotools import mask as mask_utils

from usl.geometry.cameras import project, relative_transform, scale_intrinsics, transform_points, unproject

from .grid import nearest_index, pixel_centres, resample_nearest
from .masks import RLE


def encode(mask: np.ndarray) -> RLE:
    return mask_utils.encode(np.asfortranarray(mask, dtype=np.uint8))


class DepthWarp:
    """Correspondences from recent frames into the current one.

    Call ``add_frame`` for every processed frame (it becomes the current one), then ``warp`` masks
    of earlier frames into it. Masks may have any resolution covering the colour frame (the mask
    source's); results come back at that resolution. ``retain`` drops frames no track refers to any
    more, so memory holds only a few depth maps whatever the scan length.
    """

    def __init__(self, K: np.ndarray, width: int, height: int, tolerance: float = 0.2, max_side: int = 320):
        """``K``, ``width``, ``height``: the camera of the depth maps given to ``add_frame``."""
        self.size = (width, height)
        factor = max(1.0, max(width, height) / max_side)
        self.width, self.height = max(1, round(width / factor)), max(1, round(height / factor))
        K = torch.as_tensor(np.asarray(K, dtype=np.float64))
        self.K = scale_intrinsics(K, self.width / width, self.height / height)
        self.tolerance = tolerance
        self._uv = torch.as_tensor(pixel_centres(self.width, self.height))
        self._frames: dict[int, tuple[np.ndarray, torch.Tensor]] = {}
        self._current: int | None = None
        self._pairs: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray] | None] = {}
        self._covered: dict[tuple[int, int, int], RLE] = {}

    def add_frame(self, index: int, depth: np.ndarray, cam_to_world: np.ndarray) -> None:
        """``depth``: (height, width) metres with NaN unknown; ``cam_to_world``: 4x4."""
        if depth.shape != (self.size[1], self.size[0]):
            raise ValueError(f"depth {depth.shape} does not match the {self.size[0]}x{self.size[1]} camera")
        coarse = resample_nearest(depth, self.height, self.width)
        self._frames[index] = (coarse.ravel(), torch.as_tensor(np.asarray(cam_to_world, dtype=np.float64)))
        self._current = index
        self._pairs, self._covered = {}, {}

    def retain(self, indices: set[int]) -> None:
        keep = set(indices) | {self._current}
        self._frames = {i: f for i, f in self._frames.items() if i in keep}

    def _correspondences(self, source: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """(current warp-grid pixels, their source pixels, covered-pixel mask) or None."""
        if source not in self._pairs:
            self._pairs[source] = self._compute(source)
        return self._pairs[source]

    def _compute(self, source: int) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        if source not in self._frames or self._current is None:
            return None
        depth_t, pose_t = self._frames[self._current]
        depth_s, pose_s = self._frames[source]
        target = np.flatnonzero(np.isfinite(depth_t) & (depth_t > 0))
        points = unproject(self._uv[target], torch.as_tensor(depth_t[target], dtype=torch.float64), self.K)
        points = transform_points(points, relative_transform(pose_t, pose_s))
        uv, w = project(points, self.K)
        src = nearest_index(uv.numpy(), self.width, self.height)
        seen = np.append(depth_s, np.float32(np.nan))[src]
        agree = (src >= 0) & (w.numpy() > 0) & (np.abs(seen - w.numpy()) < self.tolerance)
        target, src = target[agree], src[agree]
        covered = np.zeros(self.width * self.height, np.uint8)
        covered[target] = 1
        return target, src, covered.reshape(self.height, self.width)

    def covered(self, source: int, height: int, width: int) -> RLE | None:
        """The current pixels (of a height x width mask frame) the warp from ``source`` is defined on."""
        pair = self._correspondences(source)
        if pair is None:
            return None
        key = (source, height, width)
        if key not in self._covered:
            self._covered[key] = encode(resample_nearest(pair[2], height, width))
        return self._covered[key]

    def warp(self, source: int, rle: RLE) -> RLE | None:
        """A source-frame mask as seen from the current frame (same resolution); None if unknown source."""
        pair = self._correspondences(source)
        if pair is None:
            return None
        target, src, _ = pair
        height, width = rle["size"]
        coarse = np.ascontiguousarray(resample_nearest(mask_utils.decode(rle), self.height, self.width))
        moved = np.zeros(self.width * self.height, np.uint8)
        moved[target] = coarse.ravel()[src]
        return encode(resample_nearest(moved.reshape(self.height, self.width), height, width))
