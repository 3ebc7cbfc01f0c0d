"""Reading one frame's raw arrays, from the released HDF5 files or from renderer EXR files.

Both readers return the same ``RawFrame``; everything downstream is format-agnostic. A frame that
cannot be read raises ``FrameSkip`` with the offending file.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np
import OpenEXR

from .paths import FrameSkip, TrajectoryPaths

EXR_COLOUR = ("R", "G", "B")
EXR_ENTITY = "VRayRenderEntityID"
EXR_POSITION = ("VRayPosition.R", "VRayPosition.G", "VRayPosition.B")


@dataclass
class RawFrame:
    rgb: np.ndarray  # (H, W, 3) float32, linear HDR radiance
    entity: np.ndarray  # (H, W) int, render entity id, -1 where no geometry
    distance: np.ndarray  # (H, W) float32, Euclidean distance to the camera centre in metres, NaN unknown
    semantic: np.ndarray  # (H, W) int, NYU40 id, -1 unlabelled
    instance: np.ndarray  # (H, W) int, scene-global instance id, -1 none

    def check(self, width: int, height: int, where: Path) -> None:
        """Shapes must agree with each other and with the scene's camera model."""
        shapes = {
            "color": self.rgb.shape[:2],
            "render_entity_id": self.entity.shape,
            "depth": self.distance.shape,
            "semantic": self.semantic.shape,
            "semantic_instance": self.instance.shape,
        }
        if self.rgb.ndim != 3 or self.rgb.shape[2] != 3 or len(set(shapes.values())) != 1:
            listing = ", ".join(f"{k} {v}" for k, v in shapes.items())
            raise FrameSkip(f"frame arrays disagree in shape ({listing})", where)
        if self.distance.shape != (height, width):
            h, w = self.distance.shape
            raise FrameSkip(f"frame is {w}x{h} but the camera CSV says {width}x{height}", where)


def _integer_labels(array: np.ndarray, path: Path) -> np.ndarray:
    if not np.issubdtype(array.dtype, np.integer):
        raise FrameSkip(f"labels stored as {array.dtype}, expected integers", path)
    return array


def _open_dataset(path: Path, what: str, read):
    if not path.is_file():
        raise FrameSkip(f"missing {what} file", path)
    try:
        with h5py.File(path, "r") as f:
            return read(f["dataset"])
    except (OSError, KeyError, ValueError) as exc:
        raise FrameSkip(f"unreadable {what} HDF5 ({type(exc).__name__})", path) from None


def read_hdf5(path: Path, what: str) -> np.ndarray:
    """The ``dataset`` array of one Hypersim HDF5 file."""
    return _open_dataset(path, what, lambda d: d[()])


def _float32_channels(dataset: h5py.Dataset) -> np.ndarray:
    """An (H, W, C) dataset as float32, one channel at a time: Hypersim's chunks are (.., .., 1), and
    reading channel planes then interleaving is ~1.5x faster than HDF5 scattering the whole array."""
    if dataset.ndim != 3:
        return dataset[()].astype(np.float32)
    out = np.empty(dataset.shape, np.float32)
    for channel in range(dataset.shape[2]):
        out[..., channel] = dataset[:, :, channel]
    return out


def _labels(paths: TrajectoryPaths, frame: int) -> tuple[np.ndarray, np.ndarray]:
    semantic_file = paths.geometry_hdf5(frame, "semantic")
    instance_file = paths.geometry_hdf5(frame, "semantic_instance")
    return (
        _integer_labels(read_hdf5(semantic_file, "semantic"), semantic_file),
        _integer_labels(read_hdf5(instance_file, "semantic_instance"), instance_file),
    )


def read_hdf5_frame(paths: TrajectoryPaths, frame: int) -> RawFrame:
    """The released layout: colour, distance, entity and label images as float16/int16 HDF5."""
    entity_file = paths.geometry_hdf5(frame, "render_entity_id")
    distance = read_hdf5(paths.geometry_hdf5(frame, "depth_meters"), "depth_meters")
    entity = _integer_labels(read_hdf5(entity_file, "render_entity_id"), entity_file)
    semantic, instance = _labels(paths, frame)
    rgb = _open_dataset(paths.color_hdf5(frame), "color", _float32_channels)
    return RawFrame(rgb, entity, distance.astype(np.float32), semantic, instance)


def _exr_channels(path: Path, names: tuple[str, ...]) -> list[np.ndarray]:
    if not path.is_file():
        raise FrameSkip("missing EXR file", path)
    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            channels = exr.channels()
            missing = [n for n in names if n not in channels]
            if missing:
                raise FrameSkip(f"EXR lacks channel(s) {', '.join(missing)}", path)
            return [np.asarray(channels[n].pixels) for n in names]
    except FrameSkip:
        raise
    except Exception as exc:  # OpenEXR raises plain exceptions for truncated or foreign files
        raise FrameSkip(f"unreadable EXR ({type(exc).__name__})", path) from None


def _entity_ids(raw: np.ndarray, path: Path) -> np.ndarray:
    """Render entity ids as int64 with -1 where there is no geometry (id <= 0, as Hypersim does)."""
    if raw.dtype == np.uint32:
        ids = raw.view(np.int32).astype(np.int64)
    else:
        values = raw.astype(np.float64)
        if not np.isfinite(values).all():
            raise FrameSkip("non-finite render entity ids", path)
        ids = np.rint(values).astype(np.int64)
    ids[ids <= 0] = -1
    return ids


def read_exr_frame(
    paths: TrajectoryPaths, frame: int, camera_centre: np.ndarray, meters_per_asset_unit: float
) -> RawFrame:
    """Renderer EXRs: distance is ``|position - camera centre|`` in metres, as Hypersim derives it."""
    geometry_file = paths.geometry_exr(frame)
    entity_raw, *position = _exr_channels(geometry_file, (EXR_ENTITY,) + EXR_POSITION)
    entity = _entity_ids(entity_raw, geometry_file)
    offsets = np.stack([c.astype(np.float64) - camera_centre[k] for k, c in enumerate(position)], axis=-1)
    distance = (np.sqrt((offsets**2).sum(axis=-1)) * meters_per_asset_unit).astype(np.float32)
    distance[entity < 0] = np.nan
    semantic, instance = _labels(paths, frame)
    rgb = np.stack([c.astype(np.float32) for c in _exr_channels(paths.final_exr(frame), EXR_COLOUR)], axis=-1)
    return RawFrame(rgb, entity, distance, semantic, instance)
