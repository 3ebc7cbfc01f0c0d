"""The frustum homography of docs/design.md §5: normalized cube [-1, 1]^3 <-> object frustum.

The shape head predicts meshes in a normalized cube with coordinates (x, y, w). The cube
is cast into the camera frame of the input view by a true projective map (a 4x4
homography), so straight lines stay straight and the prediction is equivariant to where
the object sits in the image:

* x and y run linearly across the object's 2D box in the image,
  ``u = x0 + (x + 1) / 2 * (x1 - x0)`` and ``v = y0 + (y + 1) / 2 * (y1 - y0)``;
* w runs linearly in *inverse* depth, from the near plane ``d = z - rho/2`` (w = -1)
  to the far plane ``d = z + rho/2`` (w = +1), as in Mesh R-CNN's frustum mapping.

"Depth" here is the *homogeneous* depth ``d = (K @ X)_3`` (the divisor ``w`` returned by
``cameras.project``), and the camera point is ``X = d * K^-1 [u, v, 1]``. Because
``[K^-1 [u, v, 1]; 1/d]`` is linear in ``(x, y, w, 1)``, the map is projective for ANY
invertible K, Hypersim's tilt-shift cameras (last row of K not [0, 0, 1]) included. For
an upper-triangular K, d is the usual planar depth z of docs/design.md §2.

Guards: the near plane is clamped to at least ``MIN_NEAR_DEPTH`` so the frustum stays in
front of the camera, and the inverse depth of mapped points is clamped to at least
``MIN_INV_DEPTH``: cube points beyond ``w = 2z/rho`` (which a deformed mesh may reach, as
vertex offsets are not confined to the cube) would otherwise land at or behind infinity.
Inside the cube neither clamp is active for sensible layouts, so the map is exact there.
"""

from __future__ import annotations

import torch

from usl.geometry.cameras import pixel_rays

Tensor = torch.Tensor

# Smallest near-plane depth (metres) of a frustum: z - rho/2 is clamped to this.
MIN_NEAR_DEPTH = 1e-3
# Smallest inverse depth (1/metres) a mapped point may have, i.e. depths stay below 1e4 m.
MIN_INV_DEPTH = 1e-4
# Smallest box side (pixels) and inverse-depth span used when inverting the map.
_MIN_SPAN = 1e-9


def _inverse_depth_line(z: Tensor, rho: Tensor) -> tuple[Tensor, Tensor]:
    """Coefficients (a, b) of ``1/d = a + b * w`` with w = -1 at the near, +1 at the far plane."""
    inv_near = 1.0 / torch.clamp(z - 0.5 * rho, min=MIN_NEAR_DEPTH)
    inv_far = 1.0 / torch.clamp(z + 0.5 * rho, min=MIN_NEAR_DEPTH)
    return 0.5 * (inv_near + inv_far), 0.5 * (inv_far - inv_near)


def _box_affine(boxes: Tensor) -> tuple[Tensor, Tensor]:
    """Centre (..., 2) and half size (..., 2) of xyxy boxes: ``uv = centre + half * xy``."""
    lo, hi = boxes[..., :2], boxes[..., 2:]
    return 0.5 * (lo + hi), 0.5 * (hi - lo)


def cube_to_frustum(points_cube: Tensor, boxes: Tensor, K: Tensor, z: Tensor, rho: Tensor) -> Tensor:
    """Map normalized-cube points (x, y, w) into the camera frame of the object frustum.

    Args:
        points_cube: (..., N, 3) points in [-1, 1]^3 (points outside map by the same formula).
        boxes: (..., 4) xyxy 2D boxes in the pixel frame of docs/design.md §2.
        K: (..., 3, 3) general invertible intrinsics.
        z: (...) frustum centre depth; rho: (...) frustum depth extent (metres).
    Leading dimensions broadcast. Differentiable w.r.t. points, boxes, K, z and rho.
    Returns:
        (..., N, 3) points in the OpenCV camera frame.
    """
    centre, half = _box_affine(boxes)
    uv = centre.unsqueeze(-2) + half.unsqueeze(-2) * points_cube[..., :2]
    rays = pixel_rays(uv, K)
    a, b = _inverse_depth_line(z, rho)
    inv_depth = a.unsqueeze(-1) + b.unsqueeze(-1) * points_cube[..., 2]
    return rays / torch.clamp(inv_depth, min=MIN_INV_DEPTH).unsqueeze(-1)


def frustum_to_cube(points_cam: Tensor, boxes: Tensor, K: Tensor, z: Tensor, rho: Tensor) -> Tensor:
    """Inverse of ``cube_to_frustum``: camera-frame points (..., N, 3) -> cube points (..., N, 3).

    Points must lie in front of the camera (homogeneous depth > 0). Degenerate boxes or
    rho = 0 have no inverse; their spans are floored at a tiny epsilon to stay finite.
    """
    h = points_cam @ K.transpose(-1, -2)
    depth = h[..., 2]
    uv = h[..., :2] / depth.unsqueeze(-1)
    centre, half = _box_affine(boxes)
    half = torch.clamp(half, min=_MIN_SPAN)
    xy = (uv - centre.unsqueeze(-2)) / half.unsqueeze(-2)
    a, b = _inverse_depth_line(z, rho)
    b = torch.where(b.abs() < _MIN_SPAN, torch.full_like(b, -_MIN_SPAN), b)
    w = (1.0 / depth - a.unsqueeze(-1)) / b.unsqueeze(-1)
    return torch.cat([xy, w.unsqueeze(-1)], dim=-1)


def frustum_homography(boxes: Tensor, K: Tensor, z: Tensor, rho: Tensor) -> Tensor:
    """The 4x4 matrix H with ``[X; 1] ~ H @ [x, y, w, 1]`` (before the inverse-depth clamp).

    ``H = [[K^-1 @ A], [0, 0, b, a]]`` where A (3x4) takes (x, y, w, 1) to the pixel
    ``[u, v, 1]`` and ``1/d = a + b * w``. Shape (..., 4, 4), leading dims broadcast.
    ``cube_to_frustum`` evaluates the same map without forming H.
    """
    centre, half = _box_affine(boxes)
    a, b = _inverse_depth_line(z, rho)
    batch = torch.broadcast_shapes(boxes.shape[:-1], K.shape[:-2], z.shape, rho.shape)
    dtype, device = torch.result_type(boxes, K), boxes.device
    pixel = torch.zeros(*batch, 3, 4, dtype=dtype, device=device)
    pixel[..., 0, 0] = half[..., 0]
    pixel[..., 0, 3] = centre[..., 0]
    pixel[..., 1, 1] = half[..., 1]
    pixel[..., 1, 3] = centre[..., 1]
    pixel[..., 2, 3] = 1.0
    bottom = torch.zeros(*batch, 1, 4, dtype=dtype, device=device)
    bottom[..., 0, 2] = b
    bottom[..., 0, 3] = a
    return torch.cat([torch.linalg.inv(K) @ pixel, bottom], dim=-2)
