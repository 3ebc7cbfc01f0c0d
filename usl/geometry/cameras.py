"""Camera conventions of docs/design.md §2, in one place.

OpenCV axes (x right, y down, z forward), pixel centres at +0.5, and a *general*
3x3 ``K`` applied with a homogeneous divide, so Hypersim's tilt-shift cameras work
everywhere. Every function is batched over leading dimensions and differentiable.
Works on torch tensors; numpy callers convert with ``torch.as_tensor``.
"""

from __future__ import annotations

import numpy as np
import torch

from usl.utils.transfer import to_device

Tensor = torch.Tensor

# Points with a homogeneous depth below this are treated as behind the camera.
MIN_DEPTH = 1e-6


def to_homogeneous(points: Tensor) -> Tensor:
    """Append a column of ones: (..., D) -> (..., D+1)."""
    return torch.cat([points, torch.ones_like(points[..., :1])], dim=-1)


def project(points_cam: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
    """Project camera-frame points with a full 3x3 ``K``.

    Args:
        points_cam: (..., N, 3) points in the OpenCV camera frame.
        K: (..., 3, 3) intrinsics, broadcastable against ``points_cam``'s batch dims.
    Returns:
        uv: (..., N, 2) continuous pixel coordinates (top-left pixel centre = (0.5, 0.5)).
        w:  (..., N) the homogeneous divisor; equals planar depth z when K's last row is
            [0, 0, 1]. ``w <= 0`` means behind the camera; ``uv`` is then meaningless.
    """
    h = points_cam @ K.transpose(-1, -2)
    w = h[..., 2]
    safe_w = torch.where(w.abs() < MIN_DEPTH, torch.full_like(w, MIN_DEPTH), w)
    return h[..., :2] / safe_w.unsqueeze(-1), w


def pixel_rays(uv: Tensor, K: Tensor) -> Tensor:
    """Rays ``K^-1 [u, v, 1]`` (..., N, 3) through pixels (..., N, 2); scaled so ``(K X)_3 = 1``."""
    return to_homogeneous(uv) @ torch.linalg.inv(K).transpose(-1, -2)


def unproject(uv: Tensor, depth: Tensor, K: Tensor) -> Tensor:
    """Back-project pixels with *planar* depth (camera-frame z) to camera-frame points.

    Inverts ``project`` exactly for any invertible K (tilt-shift included): the ray is
    ``K^-1 [u, v, 1]``, scaled so its z component equals ``depth``.
    Args:
        uv: (..., N, 2) pixel coordinates; depth: (..., N) planar depth; K: (..., 3, 3).
    """
    rays = pixel_rays(uv, K)
    return rays * (depth / rays[..., 2]).unsqueeze(-1)


def transform_points(points: Tensor, transform: Tensor) -> Tensor:
    """Apply a 4x4 rigid transform (..., 4, 4) to points (..., N, 3)."""
    return points @ transform[..., :3, :3].transpose(-1, -2) + transform[..., None, :3, 3]


def relative_transform(cam_to_world_src: Tensor, cam_to_world_dst: Tensor) -> Tensor:
    """``R_{src->dst} = inv(cam_to_world_dst) @ cam_to_world_src`` (docs/design.md §2).

    Takes points in camera ``src``'s frame to camera ``dst``'s frame.
    """
    return rigid_inverse(cam_to_world_dst) @ cam_to_world_src


def rigid_inverse(transform: Tensor) -> Tensor:
    """Inverse of a 4x4 rigid transform without a general matrix inverse."""
    rot_t = transform[..., :3, :3].transpose(-1, -2)
    out = torch.zeros_like(transform)
    out[..., :3, :3] = rot_t
    out[..., :3, 3] = -(rot_t @ transform[..., :3, 3:4]).squeeze(-1)
    out[..., 3, 3] = 1.0
    return out


def intrinsics_from_fov(fov_x: float, width: int, height: int) -> Tensor:
    """Upper-triangular K for a centred principal point and square pixels (float64)."""
    import math

    f = 0.5 * width / math.tan(0.5 * fov_x)
    return torch.tensor([[f, 0.0, 0.5 * width], [0.0, f, 0.5 * height], [0.0, 0.0, 1.0]], dtype=torch.float64)


def scale_intrinsics(K: Tensor, sx: float, sy: float) -> Tensor:
    """K for an image resized by (sx, sy) under the +0.5 pixel-centre convention.

    With pixel centres at +0.5 the image spans [0, W]x[0, H], so resizing is a pure
    scale of the pixel frame: ``K' = diag(sx, sy, 1) @ K`` (no half-pixel shift).
    """
    S = torch.diag(to_device([sx, sy, 1.0], K.device, K.dtype))
    return S @ K


def opencv_to_opengl_camera() -> Tensor:
    """diag(1, -1, -1, 1): flips OpenCV camera axes to OpenGL's (y up, looking down -z)."""
    return torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


def look_at(
    eye: np.ndarray, target: np.ndarray, up: np.ndarray | tuple[float, float, float] = (0.0, 1.0, 0.0)
) -> np.ndarray:
    """cam_to_world (4x4 float64 numpy) of an OpenCV camera at ``eye`` looking at ``target``.

    ``up`` is the world's up direction (Y-up worlds: (0, 1, 0); Z-up, e.g. ScanNet: (0, 0, 1)); the
    camera's y axis points away from it. Numpy because pipelines build poses before any tensor exists.
    """
    eye, target, up = (np.asarray(a, dtype=np.float64) for a in (eye, target, up))
    forward = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    down = np.cross(forward, right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, down, forward, eye
    return pose
