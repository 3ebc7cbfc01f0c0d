"""One camera trajectory of one Hypersim scene -> one record scene (``build_trajectory``).

Per frame: pose, raw arrays, tone-mapped colour, planar depth, instance masks at the output
resolution. Categories are decided once per trajectory from the NYU40 votes of all converted
frames, so an instance has the same category in every view; then the exclusion and minimum-size
rules are applied and counted.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch

from usl.geometry.cameras import scale_intrinsics
from usl.records import SceneRecord, Skip, encode_depth, encode_image, frame_row

from .camera import Trajectory, intrinsics_from_m_cam_from_uv, load_trajectory, planar_depth_factor
from .frames import RawFrame, read_exr_frame, read_hdf5_frame
from .instances import category_votes, instance_entries
from .metadata import CameraModel, read_meters_per_asset_unit
from .paths import FrameSkip, TrajectoryPaths
from .resample import Resampler
from .tonemap import apply_tonemap, tonemap_scale

UNLABELLED_REASON = "instance without an NYU40 label"


@dataclass(frozen=True)
class ConvertOptions:
    input_format: str = "hdf5"
    resolution: tuple[int, int] | None = None  # (width, height) of the records; None: as rendered
    image_codec: str = "jpeg"
    image_quality: int = 95
    min_instance_pixels: int = 100  # at the stored resolution
    excluded_categories: tuple[int, ...] = ()
    store_depth: bool = True


@dataclass(frozen=True)
class TrajectoryUnit:
    """Everything ``build_trajectory`` needs, picklable for the worker processes."""

    scene: str
    camera: str
    scene_dir: str
    camera_model: CameraModel
    frames: tuple[int, ...]
    planned_skips: tuple[tuple[str, str, int], ...]  # (reason, path, count), e.g. official exclusions
    options: ConvertOptions

    @property
    def scene_id(self) -> str:
        return f"{self.scene}/{self.camera}"


@dataclass
class ConvertedFrame:
    """A frame waiting for the trajectory's categories."""

    view_id: int
    image: bytes
    depth: bytes | None
    pose: np.ndarray
    entries: list[dict[str, Any]]
    vote_ids: np.ndarray
    votes: np.ndarray


class TrajectoryConverter:
    """Per-trajectory state (units, keyframes, K, depth factors, resampler) and the per-frame work."""

    def __init__(self, unit: TrajectoryUnit):
        self.unit = unit
        self.options = unit.options
        self.paths = TrajectoryPaths(Path(unit.scene_dir), unit.camera)
        self.meters_per_asset_unit = read_meters_per_asset_unit(Path(unit.scene_dir))
        self.trajectory: Trajectory = load_trajectory(self.paths)
        model = unit.camera_model
        width, height = self.options.resolution or (model.width, model.height)
        native_K = intrinsics_from_m_cam_from_uv(model.matrix, model.width, model.height)
        self.K = scale_intrinsics(torch.from_numpy(native_K), width / model.width, height / model.height).numpy()
        self.depth_factor = planar_depth_factor(model.matrix, model.width, model.height)
        self.resampler = Resampler(model.width, model.height, width, height, native_K)
        self.size = (width, height)

    def read(self, frame: int) -> tuple[RawFrame, Path]:
        if self.options.input_format == "exr":
            centre = self.trajectory.positions[self.trajectory.row(frame)]
            raw = read_exr_frame(self.paths, frame, centre, self.meters_per_asset_unit)
            return raw, self.paths.geometry_exr(frame)
        return read_hdf5_frame(self.paths, frame), self.paths.geometry_hdf5(frame, "depth_meters")

    def convert(self, frame: int) -> ConvertedFrame:
        pose = self.trajectory.camera_to_world(frame, self.meters_per_asset_unit)
        raw, geometry_file = self.read(frame)
        model = self.unit.camera_model
        raw.check(model.width, model.height, geometry_file)
        valid = raw.entity != -1
        planar = raw.distance * self.depth_factor
        with np.errstate(invalid="ignore"):
            planar[~(valid & (planar > 0) & np.isfinite(planar))] = np.nan
        if np.isnan(planar).all():
            raise FrameSkip("no valid geometry in frame", geometry_file)
        vote_ids, votes = category_votes(raw.instance, raw.semantic)
        rgb = apply_tonemap(self.resampler.colour(raw.rgb), tonemap_scale(raw.rgb, valid))
        depth = self.resampler.depth(planar)
        entries = instance_entries(self.resampler.labels(raw.instance), depth)
        image = encode_image(rgb, self.options.image_codec, self.options.image_quality)
        depth_png = encode_depth(depth) if self.options.store_depth else None
        return ConvertedFrame(frame, image, depth_png, pose, entries, vote_ids, votes)


def trajectory_categories(frames: list[ConvertedFrame]) -> dict[int, int]:
    """Instance id -> majority NYU40 label over all its labelled pixels (ties: smaller id)."""
    totals: dict[int, np.ndarray] = {}
    for frame in frames:
        for instance_id, votes in zip(frame.vote_ids.tolist(), frame.votes, strict=True):
            totals[instance_id] = totals.get(instance_id, 0) + votes
    return {i: int(np.argmax(v[1:])) + 1 for i, v in totals.items() if v[1:].sum() > 0}


def _rows(
    unit: TrajectoryUnit, K: np.ndarray, size: tuple[int, int], frames: list[ConvertedFrame]
) -> tuple[list[dict[str, Any]], list[Skip]]:
    options = unit.options
    categories = trajectory_categories(frames)
    excluded = set(options.excluded_categories)
    unlabelled = small = 0
    rows = []
    for frame in frames:
        instances = []
        for entry in frame.entries:
            category = categories.get(entry["instance_id"])
            if category is None:
                unlabelled += 1
            elif category in excluded:
                continue
            elif entry["area"] < options.min_instance_pixels:
                small += 1
            else:
                instances.append({**entry, "category_id": category})
        rows.append(
            frame_row(
                unit.scene_id, frame.view_id, frame.image, K, frame.pose, instances, size[1], size[0], frame.depth
            )
        )
    skips = []
    if unlabelled:
        skips.append(Skip(UNLABELLED_REASON, unit.scene_id, unlabelled))
    if small:
        skips.append(Skip(f"instance smaller than {options.min_instance_pixels} pixels", unit.scene_id, small))
    return rows, skips


def missing_image_folders(unit: TrajectoryUnit) -> list[Path]:
    """Image folders of the trajectory that do not exist (a trajectory that was not downloaded)."""
    paths, probe = TrajectoryPaths(Path(unit.scene_dir), unit.camera), unit.frames[0]
    if unit.options.input_format == "exr":
        files = [paths.final_exr(probe), paths.geometry_exr(probe)]
    else:
        files = [paths.color_hdf5(probe), paths.geometry_hdf5(probe, "depth_meters")]
    return [f.parent for f in files if not f.parent.is_dir()]


def single_threaded_worker() -> None:
    """Worker initializer: one OpenCV thread per process, so ``--workers N`` uses N cores, not N^2."""
    cv2.setNumThreads(1)
    torch.set_num_threads(1)


def build_trajectory(unit: TrajectoryUnit) -> SceneRecord:
    """The record scene ``<scene>/<camera>``; the driver's ``build_scene`` (runs in worker processes)."""
    skips = [Skip(reason, path, count) for reason, path, count in unit.planned_skips]
    if not unit.frames:
        return SceneRecord(unit.scene_id, [], skips=skips)
    missing = missing_image_folders(unit)
    if missing:
        skips.append(Skip("missing image folder", str(missing[0]), len(unit.frames)))
        return SceneRecord(unit.scene_id, [], skips=skips)
    converter = TrajectoryConverter(unit)
    converted = []
    for frame in unit.frames:
        try:
            converted.append(converter.convert(frame))
        except FrameSkip as skip:
            skips.append(Skip(skip.reason, skip.path))
    rows, instance_skips = _rows(unit, converter.K, converter.size, converted)
    return SceneRecord(unit.scene_id, rows, skips=skips + instance_skips)
