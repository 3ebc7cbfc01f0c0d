"""What every ScanNet scan reader provides, whichever the storage (``.sens`` or exported folders).

A reader is opened once per scan, reads one frame at a time on request, and never holds decoded
frames: memory stays flat in scan length. Intrinsics are converted to docs/design.md's pixel-centre
convention on reading (ScanNet, like OpenCV, puts pixel centres at integers: +0.5 shift).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np

from usl.errors import UslError
from usl.records import decode_image

# A pose whose rotation is this far from orthonormal is not float32 noise but a broken pose.
MAX_ROTATION_ERROR = 1e-2


@dataclass(frozen=True)
class Calibration:
    """Both cameras of a scan. Sizes are (width, height); K are 3x3 with pixel centres at +0.5."""

    color_size: tuple[int, int]
    depth_size: tuple[int, int]
    K_color: np.ndarray
    K_depth: np.ndarray
    depth_shift: float  # stored depth value per metre (1000: millimetres)
    has_depth: bool = True  # False: a capture without depth (K_depth, depth_size then repeat the colour's)


class Scan(Protocol):
    scene_id: str
    path: Path
    calibration: Calibration
    frame_indices: list[int]

    @property
    def color_size(self) -> tuple[int, int]: ...
    def pose(self, index: int) -> np.ndarray: ...
    def color_encoded(self, index: int) -> bytes | None: ...
    def color(self, index: int) -> np.ndarray: ...
    def depth(self, index: int) -> np.ndarray | None: ...
    def close(self) -> None: ...
    def __enter__(self) -> Scan: ...
    def __exit__(self, *exc: object) -> None: ...


def half_pixel_intrinsics(K4: np.ndarray, source: object) -> np.ndarray:
    """ScanNet's 4x4 intrinsic matrix (integer pixel centres) -> 3x3 K with centres at +0.5."""
    K4 = np.asarray(K4, dtype=np.float64)
    if K4.shape not in ((4, 4), (3, 3)) or not np.isfinite(K4).all():
        raise UslError(f"{source}: intrinsic matrix is not a finite 3x3 or 4x4 matrix")
    K = K4[:3, :3].copy()
    if abs(np.linalg.det(K)) < 1e-9:
        raise UslError(f"{source}: intrinsic matrix is singular")
    shift = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    return shift @ K


def check_registered(extrinsic_color: np.ndarray, extrinsic_depth: np.ndarray, source: object) -> None:
    """ScanNet's depth is registered to the colour camera (equal extrinsics); anything else we refuse."""
    if not np.allclose(np.asarray(extrinsic_color), np.asarray(extrinsic_depth), atol=1e-3):
        raise UslError(
            f"{source}: colour and depth extrinsics differ, so depth is not registered to the colour camera "
            "(ScanNet scans are); this converter cannot reproject unregistered depth"
        )


def check_aspect(color_size: tuple[int, int], depth_size: tuple[int, int], source: object) -> None:
    """Registered colour and depth see the same field of view: their aspect ratios must agree."""
    (cw, ch), (dw, dh) = color_size, depth_size
    if min(cw, ch, dw, dh) <= 0:
        raise UslError(f"{source}: colour {cw}x{ch} or depth {dw}x{dh} size is empty")
    if abs((cw / ch) / (dw / dh) - 1.0) > 0.02:
        raise UslError(f"{source}: colour {cw}x{ch} and depth {dw}x{dh} do not have the same aspect ratio")


def rigid_pose(raw: np.ndarray) -> np.ndarray | None:
    """A camera-to-world pose cleaned of float32 rounding, or None if it is invalid.

    Invalid: any non-finite entry (ScanNet marks lost tracking with -inf), a last row other than
    [0, 0, 0, 1], or a rotation further than ``MAX_ROTATION_ERROR`` from orthonormal. Valid rotations
    are projected onto SO(3) so that float32-stored poses pass a strict rigidity check.
    """
    pose = np.asarray(raw, dtype=np.float64).reshape(4, 4)
    if not np.isfinite(pose).all() or np.abs(pose[3] - [0.0, 0.0, 0.0, 1.0]).max() > 1e-6:
        return None
    rot = pose[:3, :3]
    if np.abs(rot.T @ rot - np.eye(3)).max() > MAX_ROTATION_ERROR or np.linalg.det(rot) <= 0:
        return None
    u, _, vt = np.linalg.svd(rot)
    out = np.eye(4)
    out[:3, :3] = u @ vt
    out[:3, 3] = pose[:3, 3]
    return out


def encoded_image_size(data: bytes) -> tuple[int, int] | None:
    """(width, height) from a PNG or JPEG header without decoding the pixels; None if neither."""
    if data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) >= 24:
        width, height = struct.unpack(">II", data[16:24])
        return int(width), int(height)
    if data[:2] != b"\xff\xd8":
        return None
    pos = 2
    while pos + 4 <= len(data):
        if data[pos] != 0xFF:
            return None
        marker = data[pos + 1]
        if marker == 0xFF:  # fill byte
            pos += 1
            continue
        if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:  # markers without a length
            pos += 2
            continue
        (length,) = struct.unpack(">H", data[pos + 2 : pos + 4])
        # SOF0..SOF15 except DHT (C4), JPG (C8) and DAC (CC) carry the frame size
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
            if pos + 9 > len(data):
                return None
            height, width = struct.unpack(">HH", data[pos + 5 : pos + 9])
            return int(width), int(height)
        pos += 2 + length
    return None


def depth_metres(raw: np.ndarray, depth_shift: float) -> np.ndarray | None:
    """Stored uint16 depth -> float32 metres with NaN where unknown (0); None if no pixel has depth."""
    if not raw.any():
        return None
    depth = raw.astype(np.float32) / np.float32(depth_shift)
    depth[raw == 0] = np.nan
    return depth


def decode_color(data: bytes, source: object) -> np.ndarray:
    """JPEG/PNG bytes -> (H, W, 3) RGB uint8, or a UslError naming the source."""
    try:
        return decode_image(data)
    except UslError as exc:
        raise UslError(f"{source}: colour image does not decode ({exc})") from None
