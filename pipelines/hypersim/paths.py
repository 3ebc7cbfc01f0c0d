"""Where Hypersim keeps each file of a scene, a camera trajectory and a frame.

HDF5 layout (the public release)::

    ai_VVV_NNN/_detail/metadata_scene.csv
    ai_VVV_NNN/_detail/cam_XX/camera_keyframe_{positions,orientations,frame_indices}.hdf5
    ai_VVV_NNN/images/scene_cam_XX_final_hdf5/frame.IIII.color.hdf5
    ai_VVV_NNN/images/scene_cam_XX_geometry_hdf5/frame.IIII.<kind>.hdf5
        kind: depth_meters, render_entity_id, semantic, semantic_instance

EXR layout (renderer output converted with ``vrimg2exr``, in the renderer's own folders)::

    ai_VVV_NNN/images/scene_cam_XX_final/frame.IIII.exr       channels R, G, B (linear HDR)
    ai_VVV_NNN/images/scene_cam_XX_geometry/frame.IIII.exr    channels VRayRenderEntityID, VRayPosition.{R,G,B}
    ai_VVV_NNN/images/scene_cam_XX_geometry_hdf5/frame.IIII.{semantic,semantic_instance}.hdf5

EXR carries render-entity ids only; the NYU40 and instance labels come from Hypersim's mesh metadata,
so the two label images must sit beside the EXR files exactly as in the HDF5 layout.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

INPUT_FORMATS = ("hdf5", "exr")  # the two layouts above

SCENE_NAME = re.compile(r"^ai_\d{3}_\d{3}$")
CAMERA_NAME = re.compile(r"^cam_\d{2}$")


class FrameSkip(Exception):
    """A frame that cannot be converted; becomes a ``Skip`` (reason + file) in the manifest."""

    def __init__(self, reason: str, path: Path | str):
        super().__init__(f"{path}: {reason}")
        self.reason = reason
        self.path = str(path)


def scene_metadata_file(scene_dir: Path) -> Path:
    return Path(scene_dir) / "_detail" / "metadata_scene.csv"


@dataclass(frozen=True)
class TrajectoryPaths:
    scene_dir: Path
    camera: str

    @property
    def detail(self) -> Path:
        return Path(self.scene_dir) / "_detail" / self.camera

    def keyframes(self, what: str) -> Path:
        """``what``: positions, orientations or frame_indices."""
        return self.detail / f"camera_keyframe_{what}.hdf5"

    def _images(self, suffix: str) -> Path:
        return Path(self.scene_dir) / "images" / f"scene_{self.camera}_{suffix}"

    def color_hdf5(self, frame: int) -> Path:
        return self._images("final_hdf5") / f"frame.{frame:04d}.color.hdf5"

    def geometry_hdf5(self, frame: int, kind: str) -> Path:
        return self._images("geometry_hdf5") / f"frame.{frame:04d}.{kind}.hdf5"

    def final_exr(self, frame: int) -> Path:
        return self._images("final") / f"frame.{frame:04d}.exr"

    def geometry_exr(self, frame: int) -> Path:
        return self._images("geometry") / f"frame.{frame:04d}.exr"
