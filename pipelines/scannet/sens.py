"""Lazy reader of ScanNet ``.sens`` files (version 4; layout in SensReader/c++/src/sensorData.h).

``.sens`` files are several GB, so the reader indexes frame offsets once (one 96-byte header read
per frame, which also finds a truncated file before any work is done) and then reads each frame's
payload with ``os.pread`` when asked: no mmap pages accumulate, memory stays flat in scan length.
"""

from __future__ import annotations

import os
import struct
import zlib
from pathlib import Path

import numpy as np

from usl.errors import UslError

from .scan import (
    Calibration,
    check_aspect,
    check_registered,
    decode_color,
    depth_metres,
    encoded_image_size,
    half_pixel_intrinsics,
)

SENS_VERSION = 4
COLOR_CODECS = {-1: "unknown", 0: "raw", 1: "png", 2: "jpeg"}
DEPTH_CODECS = {-1: "unknown", 0: "raw_ushort", 1: "zlib_ushort", 2: "occi_ushort"}
FRAME_HEADER = struct.Struct("<16f4Q")  # camera_to_world, colour/depth timestamps, colour/depth byte counts
MAX_NAME_BYTES = 1 << 16


class SensScan:
    """One ``.sens`` file. Frames are addressed by their index in the file (0..n-1)."""

    def __init__(self, path: str | Path, scene_id: str | None = None):
        self.path = Path(path)
        self.scene_id = scene_id or self.path.stem
        self._fd = os.open(self.path, os.O_RDONLY)
        try:
            self._file_size = os.fstat(self._fd).st_size
            header_end = self._read_header()
            self._index_frames(header_end)
        except BaseException:
            os.close(self._fd)
            raise
        self.frame_indices = list(range(self.num_frames))

    # -- header and index -------------------------------------------------------------------
    def _read(self, offset: int, size: int, what: str) -> bytes:
        data = os.pread(self._fd, size, offset)
        if len(data) != size:
            raise UslError(
                f"{self.path}: truncated .sens file: {what} needs bytes {offset}..{offset + size}, "
                f"file has {self._file_size}"
            )
        return data

    def _read_header(self) -> int:
        (version,) = struct.unpack("<I", self._read(0, 4, "header"))
        if version != SENS_VERSION:
            raise UslError(f"{self.path}: .sens version {version}, expected {SENS_VERSION} (or not a .sens file)")
        (name_len,) = struct.unpack("<Q", self._read(4, 8, "header"))
        if name_len > MAX_NAME_BYTES:
            raise UslError(f"{self.path}: sensor name of {name_len} bytes: not a .sens file")
        offset = 12 + name_len
        self.sensor_name = self._read(12, name_len, "header").decode("utf-8", "replace")
        mats = np.frombuffer(self._read(offset, 256, "calibration"), "<f4").reshape(4, 4, 4).astype(np.float64)
        offset += 256
        color_codec, depth_codec, cw, ch, dw, dh, shift, num = struct.unpack(
            "<ii4IfQ", self._read(offset, 36, "header")
        )
        offset += 36
        if color_codec not in (0, 1, 2):
            raise UslError(
                f"{self.path}: colour compression {COLOR_CODECS.get(color_codec, color_codec)!r} "
                "is not supported (raw, png or jpeg)"
            )
        if depth_codec == 2:
            raise UslError(
                f"{self.path}: depth uses the proprietary occi_ushort codec, which cannot be decoded; "
                "re-export the scan with zlib_ushort depth"
            )
        if depth_codec not in (0, 1):
            raise UslError(
                f"{self.path}: depth compression {DEPTH_CODECS.get(depth_codec, depth_codec)!r} "
                "is not supported (raw_ushort or zlib_ushort)"
            )
        if not (np.isfinite(shift) and shift > 0):
            raise UslError(f"{self.path}: depth shift {shift} is not a positive number")
        check_aspect((cw, ch), (dw, dh), self.path)
        check_registered(mats[1], mats[3], self.path)
        self.color_codec = COLOR_CODECS[color_codec]
        self.depth_codec = DEPTH_CODECS[depth_codec]
        self.calibration = Calibration(
            color_size=(int(cw), int(ch)),
            depth_size=(int(dw), int(dh)),
            K_color=half_pixel_intrinsics(mats[0], f"{self.path} (intrinsic_color)"),
            K_depth=half_pixel_intrinsics(mats[2], f"{self.path} (intrinsic_depth)"),
            depth_shift=float(shift),
        )
        self.num_frames = int(num)
        return offset

    def _index_frames(self, offset: int) -> None:
        if self.num_frames * FRAME_HEADER.size > self._file_size:
            raise UslError(f"{self.path}: header claims {self.num_frames} frames, more than the file can hold")
        self._poses = np.empty((self.num_frames, 16), np.float32)
        self._offsets = np.empty(self.num_frames, np.int64)
        self._sizes = np.empty((self.num_frames, 2), np.int64)
        for i in range(self.num_frames):
            fields = FRAME_HEADER.unpack(self._read(offset, FRAME_HEADER.size, f"frame {i} header"))
            color_bytes, depth_bytes = fields[18], fields[19]
            payload = offset + FRAME_HEADER.size
            end = payload + color_bytes + depth_bytes
            if end > self._file_size:
                raise UslError(
                    f"{self.path}: truncated .sens file: frame {i} of {self.num_frames} needs bytes up to "
                    f"{end}, file has {self._file_size}"
                )
            self._poses[i] = fields[:16]
            self._offsets[i] = payload
            self._sizes[i] = (color_bytes, depth_bytes)
            offset = end

    # -- frames -----------------------------------------------------------------------------
    @property
    def color_size(self) -> tuple[int, int]:
        return self.calibration.color_size

    def pose(self, index: int) -> np.ndarray:
        """The stored camera-to-world matrix (may be all -inf: lost tracking)."""
        return self._poses[index].reshape(4, 4).astype(np.float64)

    def _color_payload(self, index: int) -> bytes:
        return self._read(int(self._offsets[index]), int(self._sizes[index, 0]), f"frame {index} colour")

    def color_encoded(self, index: int) -> bytes | None:
        """The frame's JPEG/PNG bytes exactly as stored (None for raw RGB), size-checked against the header."""
        if self.color_codec == "raw":
            return None
        data = self._color_payload(index)
        size = encoded_image_size(data)
        if size is None:
            raise UslError(f"{self.path}: frame {index} colour payload is not a {self.color_codec} image")
        if size != self.color_size:
            raise UslError(
                f"{self.path}: frame {index} colour is {size[0]}x{size[1]}, header says "
                f"{self.color_size[0]}x{self.color_size[1]} (colour/depth size mismatch)"
            )
        return data

    def color(self, index: int) -> np.ndarray:
        w, h = self.color_size
        if self.color_codec == "raw":
            data = self._color_payload(index)
            if len(data) != w * h * 3:
                raise UslError(f"{self.path}: frame {index} raw colour has {len(data)} bytes, expected {w}x{h}x3")
            return np.frombuffer(data, np.uint8).reshape(h, w, 3)
        rgb = decode_color(self.color_encoded(index), f"{self.path} frame {index}")
        if rgb.shape[:2] != (h, w):
            raise UslError(
                f"{self.path}: frame {index} colour decodes to {rgb.shape[1]}x{rgb.shape[0]}, header says {w}x{h}"
            )
        return rgb

    def depth_raw(self, index: int) -> np.ndarray | None:
        """The stored uint16 depth image (depth_size), or None when the frame has no depth payload."""
        size = int(self._sizes[index, 1])
        if size == 0:
            return None
        data = self._read(int(self._offsets[index] + self._sizes[index, 0]), size, f"frame {index} depth")
        if self.depth_codec == "zlib_ushort":
            try:
                data = zlib.decompress(data)
            except zlib.error as exc:
                raise UslError(f"{self.path}: frame {index} depth is not a valid zlib stream ({exc})") from None
        w, h = self.calibration.depth_size
        if len(data) != w * h * 2:
            raise UslError(
                f"{self.path}: frame {index} depth holds {len(data)} bytes, a {w}x{h} uint16 image "
                f"needs {w * h * 2} (colour/depth size mismatch with the header)"
            )
        return np.frombuffer(data, "<u2").reshape(h, w)

    def depth(self, index: int) -> np.ndarray | None:
        """Depth in metres (float32, NaN unknown), or None when the frame has no depth at all."""
        raw = self.depth_raw(index)
        return None if raw is None else depth_metres(raw, self.calibration.depth_shift)

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1

    def __enter__(self) -> SensScan:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass
