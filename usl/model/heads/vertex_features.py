"""Vertex-aligned features for the shape head: RoIMap (the paper) and RoIAlign + VertAlign (Mesh R-CNN).

Both take mesh vertices in the normalized cube. The frustum homography maps a cube point
(x, y, w) to a camera point whose image projection is ``box_centre + box_half_size * (x, y)``
for ANY z, rho and K (``usl.geometry.frustum``: x and y run linearly across the 2D box), so the
projection of the current mesh onto the input image needs only the boxes.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F

from usl.model.detector import MultiScaleRoIAlign
from usl.utils.transfer import constant

Tensor = torch.Tensor


def project_cube_to_image(verts_cube: Tensor, boxes: Tensor) -> Tensor:
    """(N, V, 3) cube vertices and (N, 4) xyxy boxes -> (N, V, 2) input-image pixels (u, v)."""
    centre = 0.5 * (boxes[:, None, :2] + boxes[:, None, 2:])
    half = 0.5 * (boxes[:, None, 2:] - boxes[:, None, :2])
    return centre + half * verts_cube[..., :2]


def roimap_features(
    feature_maps: Sequence[Tensor], strides: Sequence[int], verts_cube: Tensor, boxes: Tensor, image_index: Tensor
) -> Tensor:
    """RoIMap: bilinear samples straight from backbone maps at each vertex's projection, concatenated.

    Args:
        feature_maps: (B, C_k, H_k, W_k) maps of the padded image batch, map k with stride ``strides[k]``
            (one map for the FPN recipes; res2..res5 for Mesh R-CNN's ShapeNet model).
        verts_cube: (N, V, 3); boxes: (N, 4) in input pixels; image_index: (N,) image of each object.
    Returns:
        (N, V, sum C_k), the maps' channels in order. Vertices projecting outside the image get
        zeros (``padding_mode="zeros"``).
    Map k spans [0, W_k * stride_k] x [0, H_k * stride_k] pixels with cell centres at
    (i + 0.5) * stride_k, which is ``grid_sample(align_corners=False)``'s convention for normalised
    coordinates; each map is sampled at its own stride, so one projection serves all of them.
    """
    if len(feature_maps) != len(strides) or not feature_maps:
        raise ValueError(f"roimap_features: {len(feature_maps)} feature maps for {len(strides)} strides")
    num_objects, num_verts = verts_cube.shape[:2]
    if num_objects == 0:
        return feature_maps[0].new_zeros(0, num_verts, sum(m.shape[1] for m in feature_maps), dtype=torch.float32)
    uv = project_cube_to_image(verts_cube.float(), boxes.float()).reshape(-1, 2)
    image = image_index[:, None].expand(num_objects, num_verts).reshape(-1)
    # float32 even under autocast: bf16 would misplace samples by cells
    per_map = [
        _sample_bilinear(m.float(), image, uv / stride - 0.5) for m, stride in zip(feature_maps, strides, strict=True)
    ]
    return torch.cat(per_map, dim=1).reshape(num_objects, num_verts, -1)


def _sample_bilinear(feature_map: Tensor, image: Tensor, xy: Tensor) -> Tensor:
    """(P, C) bilinear samples of ``feature_map`` (B, C, H, W) at cell coordinates ``xy`` (P, 2) of
    image ``image`` (P,), cell centres at integers, zero outside: ``grid_sample(align_corners=False,
    padding_mode="zeros")``, for points of all images at once (no per-image grouping, no host read)."""
    height, width = feature_map.shape[-2:]
    corner = xy.floor()
    frac = xy - corner
    # the four taps (dx, dy) = (0, 0), (1, 0), (0, 1), (1, 1) stacked: one gather, one weighted sum
    step = constant(((0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)), xy.dtype, xy.device)
    x, y = (corner + step[:, None]).unbind(-1)  # (4, P) each
    inside = (x >= 0) & (x <= width - 1) & (y >= 0) & (y <= height - 1)
    along_x, along_y = torch.stack([1 - frac, frac]).unbind(-1)  # (2, P) each: weights of the d = 0, 1 taps
    weight = (along_x[None] * along_y[:, None]).reshape(4, -1) * inside  # (dy, dx) in the taps' order
    taps = feature_map[image, :, y.clamp(0, height - 1).long(), x.clamp(0, width - 1).long()]  # (4, P, C)
    return (taps * weight[..., None]).sum(0)


def vertalign_features(roi_features: Tensor, verts_cube: Tensor) -> Tensor:
    """VertAlign on RoIAlign features (N, C, R, R): samples at cube (x, y), zeros outside the RoI.

    With aligned RoIAlign, bin i of R spans [i, i + 1] * box_size / R, so cube x in [-1, 1] is the
    RoI grid in ``align_corners=False`` coordinates.
    """
    grid = verts_cube[:, None, :, :2].float()  # (N, 1, V, 2)
    sampled = F.grid_sample(roi_features.float(), grid, align_corners=False)  # (N, C, 1, V)
    return sampled[:, :, 0].transpose(1, 2)


def single_level_pooler(feature: str, stride: int, resolution: int) -> MultiScaleRoIAlign:
    """RoIAlign from one named backbone map (the detector's pooler class, one level)."""
    return MultiScaleRoIAlign([feature], [stride], resolution, sampling_ratio=0)
