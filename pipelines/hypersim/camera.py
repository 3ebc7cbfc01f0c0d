"""Hypersim cameras in our conventions (docs/design.md §2): intrinsics from ``M_cam_from_uv``, poses.

Hypersim casts the ray of pixel (row i, column j) as ``d = M_cam_from_uv @ [u, v, 1]`` with
``u = -1 + (2j + 1) / W`` and ``v = 1 - (2i + 1) / H``, in an OpenGL-like camera frame (x right,
y up, looking down -z). With our continuous pixel coordinates ``x = j + 0.5``, ``y = i + 0.5`` that
is ``[u, v, 1] = A @ [x, y, 1]``, and the OpenCV ray is ``F @ d`` with ``F = diag(1, -1, -1)``. So
``K = (F M A)^-1`` exactly, a general projective 3x3 for tilt-shift scenes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from usl.errors import UslError

from .paths import FrameSkip, TrajectoryPaths

GL_TO_CV = np.diag([1.0, -1.0, -1.0])
# Frame 0 of a trajectory carries the artist's camera matrix, which is not always a rotation
# (apple/ml-hypersim issue 103). Within this tolerance it is float noise and snapped to the nearest
# rotation; beyond it the frame is skipped.
ROTATION_TOL = 1e-3


def uv_from_pixels(width: int, height: int) -> np.ndarray:
    """A: continuous pixel coordinates (centres at +0.5) -> Hypersim's [u, v, 1]."""
    return np.array([[2.0 / width, 0.0, -1.0], [0.0, -2.0 / height, 1.0], [0.0, 0.0, 1.0]])


def check_camera_model(m_cam_from_uv: np.ndarray, where: str) -> None:
    """Refuse an M that is singular or casts a ray that does not point forward."""
    if abs(np.linalg.det(m_cam_from_uv)) < 1e-12:
        raise UslError(f"{where}: M_cam_from_uv is singular")
    corners = np.array([[u, v, 1.0] for u in (-1.0, 1.0) for v in (-1.0, 1.0)])
    # The ray's forward component is affine in (u, v): positive at the corners means positive everywhere.
    if ((corners @ m_cam_from_uv.T)[:, 2] >= 0).any():
        raise UslError(f"{where}: M_cam_from_uv casts rays that do not look down -z")


def intrinsics_from_m_cam_from_uv(m_cam_from_uv: np.ndarray, width: int, height: int) -> np.ndarray:
    """Full 3x3 ``K`` ([x, y, 1] ~ K @ X_cv) for a ``width`` x ``height`` image, scaled so K[2, 2] = 1."""
    K = np.linalg.inv(GL_TO_CV @ m_cam_from_uv @ uv_from_pixels(width, height))
    return K / K[2, 2]


def planar_depth_factor(m_cam_from_uv: np.ndarray, width: int, height: int) -> np.ndarray:
    """Per pixel, planar depth / ray distance = (forward component of the ray) / |ray|, float32 (H, W).

    Exact for any M, tilt-shift included, unlike the f / sqrt(x^2 + y^2 + f^2) shortcut.
    """
    j = np.arange(width, dtype=np.float64)
    i = np.arange(height, dtype=np.float64)
    u = -1.0 + (2.0 * j + 1.0) / width
    v = 1.0 - (2.0 * i + 1.0) / height
    m = m_cam_from_uv
    rays = [m[r, 0] * u[None, :] + m[r, 1] * v[:, None] + m[r, 2] for r in range(3)]
    return (-rays[2] / np.sqrt(rays[0] ** 2 + rays[1] ** 2 + rays[2] ** 2)).astype(np.float32)


def _read(path: Path) -> np.ndarray:
    if not path.is_file():
        raise UslError(f"{path}: file not found")
    try:
        with h5py.File(path, "r") as f:
            return np.asarray(f["dataset"][()])
    except (OSError, KeyError) as exc:
        raise UslError(f"{path}: unreadable HDF5 or no 'dataset' in it ({exc})") from None


@dataclass
class Trajectory:
    """One camera trajectory's keyframes, looked up by the frame number in the image file names."""

    paths: TrajectoryPaths
    positions: np.ndarray  # (N, 3) camera centres, asset units
    orientations: np.ndarray  # (N, 3, 3) R_world_from_cam, Hypersim camera axes
    row_of_frame: dict[int, int]

    def row(self, frame: int) -> int:
        if frame not in self.row_of_frame:
            raise FrameSkip(f"no camera keyframe for frame {frame}", self.paths.keyframes("frame_indices"))
        return self.row_of_frame[frame]

    def camera_to_world(self, frame: int, meters_per_asset_unit: float) -> np.ndarray:
        """4x4 OpenCV camera-to-world in metres; FrameSkip if the orientation is not a rotation."""
        row = self.row(frame)
        rot = self.orientations[row]
        error = np.abs(rot.T @ rot - np.eye(3)).max()
        if not np.isfinite(rot).all() or error > ROTATION_TOL or np.linalg.det(rot) <= 0:
            raise FrameSkip("camera orientation is not a rotation", self.paths.keyframes("orientations"))
        u, _, vt = np.linalg.svd(rot)
        pose = np.eye(4)
        pose[:3, :3] = (u @ vt) @ GL_TO_CV
        pose[:3, 3] = self.positions[row] * meters_per_asset_unit
        return pose


def load_trajectory(paths: TrajectoryPaths) -> Trajectory:
    """Read the keyframe files; without ``camera_keyframe_frame_indices.hdf5`` row i is frame i
    (Hypersim's renderer asserts exactly that)."""
    positions = _read(paths.keyframes("positions")).astype(np.float64)
    orientations = _read(paths.keyframes("orientations")).astype(np.float64)
    n = positions.shape[0] if positions.ndim == 2 else -1
    if positions.shape != (n, 3) or not np.isfinite(positions).all():
        raise UslError(f"{paths.keyframes('positions')}: expected finite (N, 3) positions, got {positions.shape}")
    if orientations.shape != (n, 3, 3):
        raise UslError(f"{paths.keyframes('orientations')}: shape {orientations.shape}, expected ({n}, 3, 3)")
    index_file = paths.keyframes("frame_indices")
    frames = _read(index_file).reshape(-1) if index_file.exists() else np.arange(n)
    if frames.shape != (n,) or len(set(frames.tolist())) != n:
        raise UslError(f"{index_file}: expected {n} distinct frame indices")
    return Trajectory(paths, positions, orientations, {int(f): row for row, f in enumerate(frames)})
