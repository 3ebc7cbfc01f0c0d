"""One capture opened for conversion: the ScanNet pipeline's ``Scan`` protocol over posed frames.

Whatever the source (``transforms.json``, a COLMAP model, SfM), the frames are served like a
ScanNet scan's, so the ScanNet pipeline's tracker, depth warp and output grid run on them
unchanged: one reference pinhole camera (``camera.Rectifier`` remaps frames that differ), poses
camera-to-world in OpenCV axes and metres (``scale`` times the source's unit), depth in metres with
NaN unknown. Files are read one frame at a time, on request, and every error names the file.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from pipelines.scannet.scan import Calibration, decode_color, depth_metres, encoded_image_size
from usl.errors import UslError

from .camera import FrameCamera, Rectifier, reference_camera
from .posed import CaptureFrame, PosedCapture

ENCODED_SUFFIXES = {".jpg", ".jpeg", ".png"}


def read_bytes(path: Path, what: str) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise UslError(f"{path}: no such file ({what})") from None
    except OSError as exc:
        raise UslError(f"{path}: cannot read {what} ({exc.strerror})") from None


class Capture:
    def __init__(self, scene_id: str, path: Path, posed: PosedCapture, scale: float = 1.0):
        """``scale``: metres per unit of the poses (``scale.metric_scale``, which reads this capture's depth)."""
        self.scene_id, self.path, self.scale = scene_id, Path(path), scale
        self.frames: dict[int, CaptureFrame] = {f.index: f for f in posed.frames}
        self.frame_indices = [f.index for f in posed.frames]
        self.image_names = sorted({f.name for f in posed.frames} | set(posed.unposed))
        self.depth_unit = posed.depth_unit
        first = posed.frames[0]
        for frame in posed.frames:
            if frame.camera.size != first.camera.size:
                raise UslError(
                    f"{frame.image}: inconsistent image sizes in {self.path}: {frame.camera.width}x"
                    f"{frame.camera.height}, but {first.image} is {first.camera.width}x{first.camera.height}"
                )
        self.reference = reference_camera([f.camera for f in posed.frames])
        self._rectifiers: dict[FrameCamera, Rectifier] = {}
        depth_frame = next((f for f in posed.frames if f.depth is not None), None)
        self.depth_size = self._depth_size(depth_frame) if depth_frame is not None else self.reference.size
        K = self.reference.matrix()
        self.calibration = Calibration(
            self.reference.size,
            self.depth_size,
            K,
            self.reference.matrix(*self.depth_size),
            1.0 / self.depth_unit,
            depth_frame is not None,
        )

    @staticmethod
    def _depth_size(frame: CaptureFrame) -> tuple[int, int]:
        assert frame.depth is not None
        size = encoded_image_size(read_bytes(frame.depth, f"depth of {frame.name}"))
        if size is None:
            raise UslError(f"{frame.depth}: not a PNG depth image")
        return size

    @property
    def color_size(self) -> tuple[int, int]:
        return self.reference.size

    def rectifier(self, index: int) -> Rectifier:
        camera = self.frames[index].camera
        if camera not in self._rectifiers:
            self._rectifiers[camera] = Rectifier(camera, self.reference)
        return self._rectifiers[camera]

    def pose(self, index: int) -> np.ndarray:
        pose = np.array(self.frames[index].cam_to_world, dtype=np.float64)
        pose[:3, 3] *= self.scale
        return pose

    def _checked_size(self, frame: CaptureFrame, size: tuple[int, int] | None, what: str) -> None:
        if size != frame.camera.size:
            found = "an unreadable size" if size is None else f"{size[0]}x{size[1]}"
            raise UslError(
                f"{frame.image}: inconsistent image sizes: the {what} is {found}, its camera says "
                f"{frame.camera.width}x{frame.camera.height}"
            )

    def color_encoded(self, index: int) -> bytes | None:
        """The stored bytes, when the frame is already on the reference camera and a JPEG or PNG."""
        frame = self.frames[index]
        if not self.rectifier(index).identity or frame.image.suffix.lower() not in ENCODED_SUFFIXES:
            return None
        data = read_bytes(frame.image, f"image of frame {frame.name}")
        self._checked_size(frame, encoded_image_size(data), "image")
        return data

    def color(self, index: int) -> np.ndarray:
        frame = self.frames[index]
        rgb = decode_color(read_bytes(frame.image, f"image of frame {frame.name}"), frame.image)
        self._checked_size(frame, (rgb.shape[1], rgb.shape[0]), "image")
        return self.rectifier(index).image(rgb)

    def raw_depth(self, index: int) -> np.ndarray | None:
        """Depth in metres (NaN unknown) on the frame's own camera, at the depth images' size."""
        frame = self.frames[index]
        if frame.depth is None:
            return None
        data = read_bytes(frame.depth, f"depth of frame {frame.name}")
        raw = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if raw is None or raw.dtype != np.uint16 or raw.ndim != 2:
            raise UslError(f"{frame.depth}: not a 16-bit single-channel depth image")
        if (raw.shape[1], raw.shape[0]) != self.depth_size:
            raise UslError(
                f"{frame.depth}: inconsistent image sizes: depth is {raw.shape[1]}x{raw.shape[0]}, "
                f"other depth images of {self.path} are {self.depth_size[0]}x{self.depth_size[1]}"
            )
        return depth_metres(raw, 1.0 / self.depth_unit)

    def depth(self, index: int) -> np.ndarray | None:
        depth = self.raw_depth(index)
        return None if depth is None else self.rectifier(index).nearest(depth, float("nan"))

    def rectify_mask(self, index: int, mask: np.ndarray) -> np.ndarray:
        """A mask over the frame's own image -> the reference camera (same resolution)."""
        return self.rectifier(index).nearest(np.ascontiguousarray(mask, dtype=np.uint8), 0)

    def close(self) -> None:
        pass

    def __enter__(self) -> Capture:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
