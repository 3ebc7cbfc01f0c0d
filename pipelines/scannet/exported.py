"""Reader of scans exported by ScanNet's SensReader (python/reader.py) into frame folders.

Layout: ``color/{i}.jpg``, ``depth/{i}.png`` (uint16, millimetres), ``pose/{i}.txt`` (4x4
camera-to-world, ``-inf`` when lost) and ``intrinsic/intrinsic_{color,depth}.txt`` (4x4; the
``extrinsic_*.txt`` files are optional). ``{i}`` is the ``.sens`` frame index, not zero-padded, so
frames are ordered numerically; an export with a frame skip simply has fewer indices.
"""

from __future__ import annotations

from pathlib import Path

import cv2
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

COLOR_SUFFIXES = (".jpg", ".jpeg", ".png")
EXPORT_DEPTH_SHIFT = 1000.0  # SensReader writes the stored uint16 values (millimetres) unchanged


def _read_matrix(path: Path) -> np.ndarray:
    try:
        matrix = np.loadtxt(path, dtype=np.float64, ndmin=2)
    except (OSError, ValueError) as exc:
        raise UslError(f"{path}: cannot read a 4x4 matrix ({exc})") from None
    if matrix.shape != (4, 4):
        raise UslError(f"{path}: expected a 4x4 matrix, found shape {matrix.shape}")
    return matrix


class ExportedScan:
    def __init__(self, root: str | Path, scene_id: str | None = None):
        self.path = Path(root)
        self.scene_id = scene_id or self.path.name
        color_dir = self.path / "color"
        files = {}
        for f in color_dir.iterdir() if color_dir.is_dir() else []:
            if f.suffix.lower() in COLOR_SUFFIXES and f.stem.isdigit():
                if int(f.stem) in files:
                    raise UslError(f"{f}: two colour files for frame {int(f.stem)}")
                files[int(f.stem)] = f
        if not files:
            raise UslError(f"{color_dir}: no colour frames named <index>.jpg")
        self.frame_indices = sorted(files)
        self._color_files = files
        intrinsic = self.path / "intrinsic"
        extrinsics = [intrinsic / f"extrinsic_{c}.txt" for c in ("color", "depth")]
        if all(p.exists() for p in extrinsics):
            check_registered(_read_matrix(extrinsics[0]), _read_matrix(extrinsics[1]), intrinsic)
        first = self.frame_indices[0]
        color_size = encoded_image_size(files[first].read_bytes())
        if color_size is None:
            raise UslError(f"{files[first]}: not a JPEG or PNG image")
        first_depth = self._depth_file(first)
        depth = self._read_depth_png(first_depth)
        depth_size = (depth.shape[1], depth.shape[0])
        check_aspect(color_size, depth_size, f"{files[first]} and {first_depth}")
        self.calibration = Calibration(
            color_size=color_size,
            depth_size=depth_size,
            K_color=half_pixel_intrinsics(_read_matrix(intrinsic / "intrinsic_color.txt"), intrinsic),
            K_depth=half_pixel_intrinsics(_read_matrix(intrinsic / "intrinsic_depth.txt"), intrinsic),
            depth_shift=EXPORT_DEPTH_SHIFT,
        )

    @property
    def color_size(self) -> tuple[int, int]:
        return self.calibration.color_size

    def _frame_file(self, folder: str, index: int, suffix: str) -> Path:
        path = self.path / folder / f"{index}{suffix}"
        if not path.is_file():
            raise UslError(f"{path}: missing, but {self._color_files[index]} exists")
        return path

    def _depth_file(self, index: int) -> Path:
        return self._frame_file("depth", index, ".png")

    @staticmethod
    def _read_depth_png(path: Path) -> np.ndarray:
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
            raise UslError(f"{path}: not a single-channel 16-bit PNG")
        return raw

    def pose(self, index: int) -> np.ndarray:
        return _read_matrix(self._frame_file("pose", index, ".txt"))

    def color_encoded(self, index: int) -> bytes:
        path = self._color_files[index]
        data = path.read_bytes()
        size = encoded_image_size(data)
        if size != self.color_size:
            what = "not a JPEG or PNG image" if size is None else f"{size[0]}x{size[1]}"
            raise UslError(
                f"{path}: colour frame is {what}, the scan's first frame is {self.color_size[0]}x{self.color_size[1]}"
            )
        return data

    def color(self, index: int) -> np.ndarray:
        rgb = decode_color(self.color_encoded(index), self._color_files[index])
        if (rgb.shape[1], rgb.shape[0]) != self.color_size:
            raise UslError(
                f"{self._color_files[index]}: decodes to {rgb.shape[1]}x{rgb.shape[0]}, "
                f"header says {self.color_size[0]}x{self.color_size[1]}"
            )
        return rgb

    def depth_raw(self, index: int) -> np.ndarray:
        path = self._depth_file(index)
        raw = self._read_depth_png(path)
        if (raw.shape[1], raw.shape[0]) != self.calibration.depth_size:
            w, h = self.calibration.depth_size
            raise UslError(f"{path}: depth is {raw.shape[1]}x{raw.shape[0]}, the scan's first frame is {w}x{h}")
        return raw

    def depth(self, index: int) -> np.ndarray | None:
        return depth_metres(self.depth_raw(index), self.calibration.depth_shift)

    def close(self) -> None:
        """Nothing is held open between frames."""

    def __enter__(self) -> ExportedScan:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
