"""One capture -> one record scene: poses from its source, metric scale, then the ScanNet pipeline's
tracking and frame encoding (``pipelines.scannet.convert.convert_scan``) on the opened capture.

What the records cannot say per frame goes to the manifest's ``provenance`` of the scene: where the
poses came from, the scale and its origin, how detections were associated into objects.
"""

from __future__ import annotations

import dataclasses
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

from pipelines.scannet.convert import ConvertOptions, convert_scan
from pipelines.scannet.masks import MaskSource
from usl.records import SceneRecord
from usl.records.build_state import STATE_DIR

from .capture import Capture
from .colmap import image_names, posed_from_reconstruction, read_colmap, read_model
from .layout import CaptureSource
from .posed import PosedCapture
from .scale import metric_scale
from .sfm import SfmOptions, run_sfm
from .transforms import read_transforms
from .video import sample_video

SKIP_UNPOSED = "frame has no pose (not registered by SfM, or not in the COLMAP model)"
SFM_SOURCE = "sfm (pycolmap: SIFT, sequential matching, incremental mapping)"


def work_dir(out: Path, scene_id: str) -> Path:
    """A capture's extracted video frames and SfM model: kept with the build's state, reused on resume."""
    return Path(out) / STATE_DIR / "captures" / scene_id


@dataclass(frozen=True)
class PoseOptions:
    scale: float | None = None  # metres per unit of the poses; None: from the source, depth or the prior
    fps: float = 3.0  # frames per second taken from a video
    sfm: SfmOptions = dataclasses.field(default_factory=SfmOptions)

    def __post_init__(self) -> None:
        if self.scale is not None and not self.scale > 0:
            raise ValueError(f"scale must be > 0, got {self.scale}")
        if not self.fps > 0:
            raise ValueError(f"fps must be > 0, got {self.fps}")


@dataclass(frozen=True)
class CaptureUnit:
    """A build unit: one capture, picklable for the build driver's worker processes."""

    scene_id: str
    scene_dir: str
    source: CaptureSource
    masks: MaskSource
    options: ConvertOptions
    poses: PoseOptions
    work: str  # work_dir(out, scene_id)
    max_side: int | None = None  # with options.size None: fit the longest side to this (None: native)


def posed_capture(unit: CaptureUnit) -> PosedCapture:
    folder, source = Path(unit.scene_dir), unit.source
    if source.kind == "transforms":
        return read_transforms(Path(source.path))
    if source.kind == "colmap":
        return read_colmap(folder, Path(source.path))
    work = Path(unit.work)
    images = Path(source.path) if source.kind == "images" else sample_video(Path(source.path), unit.poses.fps, work)
    names = image_names(images)
    model = run_sfm(images, names, work / "sfm", unit.poses.sfm)
    return posed_from_reconstruction(read_model(model), images, folder, SFM_SOURCE, names, str(model))


def fitted_size(color_size: tuple[int, int], max_side: int | None) -> tuple[int, int] | None:
    """The longest side fitted to ``max_side`` (never enlarged), the aspect ratio kept."""
    width, height = color_size
    if max_side is None or max(width, height) <= max_side:
        return None
    factor = max_side / max(width, height)
    return max(1, round(width * factor)), max(1, round(height * factor))


def build_scene(unit: CaptureUnit) -> SceneRecord:
    """The shared driver's per-unit function (top level: picklable)."""
    posed = posed_capture(unit)
    with Capture(unit.scene_id, Path(unit.scene_dir), posed) as capture:
        scale = metric_scale(posed, unit.poses.scale, capture.raw_depth, capture.color_size, unit.scene_dir)
        capture.scale = scale.metres_per_unit
        options = unit.options
        if options.size is None:
            options = dataclasses.replace(options, size=fitted_size(capture.color_size, unit.max_side))
        has_depth = capture.calibration.has_depth
        provenance = {
            "source": unit.source.kind,
            "pose_source": posed.pose_source,
            **scale.describe(),
            "depth": has_depth,
            "association": "mask IoU, depth-warped" if has_depth and options.warps else "mask IoU in place",
            "frames_posed": len(posed.frames),
            "frames_unposed": len(posed.unposed),
        }
        skips = Counter({SKIP_UNPOSED: len(posed.unposed)})
        return convert_scan(capture, unit.masks, options, skips, provenance)
