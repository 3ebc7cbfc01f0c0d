"""Hypersim's CSV metadata: the official split, per-scene camera models, per-scene units.

Every problem is a ``UslError`` naming the file, found before any frame is converted.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from usl.errors import UslError

from .paths import scene_metadata_file

SPLIT_COLUMNS = (
    "scene_name",
    "camera_name",
    "frame_id",
    "included_in_public_release",
    "exclude_reason",
    "split_partition_name",
)
M_COLUMNS = tuple(f"M_cam_from_uv_{i}{j}" for i in range(3) for j in range(3))
CAMERA_COLUMNS = ("scene_name", "settings_output_img_width", "settings_output_img_height") + M_COLUMNS


def _rows(path: Path, required: tuple[str, ...]) -> list[dict[str, str]]:
    """The rows of a CSV with the ``required`` columns, each as complete as its header."""
    path = Path(path)
    if not path.is_file():
        raise UslError(f"{path}: file not found")
    try:
        with open(path, newline="", encoding="utf-8-sig") as f:
            reader = csv.DictReader(f)
            missing = [c for c in required if c not in (reader.fieldnames or [])]
            if missing:
                raise UslError(f"{path}: missing column(s) {', '.join(missing)}")
            rows = list(reader)
    except UnicodeDecodeError as exc:
        raise UslError(f"{path}: not UTF-8 text (byte {exc.start}: {exc.reason})") from None
    except csv.Error as exc:
        raise UslError(f"{path}: not a readable CSV ({exc})") from None
    for line, row in enumerate(rows, start=2):
        if None in row or None in row.values():  # DictReader's marks for extra or missing fields
            raise UslError(f"{path}:{line}: the row has {'more' if None in row else 'fewer'} fields than the header")
    return rows


@dataclass
class TrajectorySplit:
    """What the official split says about one (scene, camera) trajectory."""

    split: str | None = None
    frames: list[int] = field(default_factory=list)  # included in the public release, ascending
    excluded: dict[str, list[int]] = field(default_factory=dict)  # exclude_reason -> frames


def read_split_csv(path: Path) -> dict[tuple[str, str], TrajectorySplit]:
    """``metadata_images_split_scene_v1.csv`` -> trajectory -> split, included frames, exclusions."""
    trajectories: dict[tuple[str, str], TrajectorySplit] = {}
    for line, row in enumerate(_rows(path, SPLIT_COLUMNS), start=2):
        key = (row["scene_name"], row["camera_name"])
        entry = trajectories.setdefault(key, TrajectorySplit())
        try:
            frame = int(row["frame_id"])
        except ValueError:
            raise UslError(f"{path}:{line}: frame_id {row['frame_id']!r} is not an integer") from None
        included = row["included_in_public_release"].strip().lower()
        if included not in ("true", "false"):
            raise UslError(f"{path}:{line}: included_in_public_release must be True or False")
        if included == "false":
            entry.excluded.setdefault(row["exclude_reason"].strip() or "excluded", []).append(frame)
            continue
        split = row["split_partition_name"].strip()
        if not split:
            raise UslError(f"{path}:{line}: included frame without a split_partition_name")
        if entry.split not in (None, split):
            raise UslError(f"{path}:{line}: {key[0]}/{key[1]} is in both {entry.split!r} and {split!r}")
        entry.split = split
        entry.frames.append(frame)
    for key, entry in trajectories.items():
        entry.frames.sort()
        if len(set(entry.frames)) != len(entry.frames):
            raise UslError(f"{path}: {key[0]}/{key[1]} lists a frame twice")
    return trajectories


@dataclass(frozen=True)
class CameraModel:
    """A scene's image size and ``M_cam_from_uv`` (row-major 3x3, maps [u, v, 1] to a camera ray)."""

    width: int
    height: int
    m_cam_from_uv: tuple[float, ...]

    @property
    def matrix(self) -> np.ndarray:
        return np.asarray(self.m_cam_from_uv, dtype=np.float64).reshape(3, 3)


def read_camera_csv(path: Path) -> dict[str, CameraModel]:
    """``metadata_camera_parameters.csv`` -> scene -> camera model."""
    models: dict[str, CameraModel] = {}
    for line, row in enumerate(_rows(path, CAMERA_COLUMNS), start=2):
        try:
            width = int(float(row["settings_output_img_width"]))
            height = int(float(row["settings_output_img_height"]))
            m = tuple(float(row[c]) for c in M_COLUMNS)
        except ValueError as exc:
            raise UslError(f"{path}:{line}: {row['scene_name']}: unparseable camera parameter ({exc})") from None
        if width < 1 or height < 1 or not np.isfinite(m).all():
            raise UslError(f"{path}:{line}: {row['scene_name']}: bad image size or non-finite M_cam_from_uv")
        models[row["scene_name"]] = CameraModel(width, height, m)
    return models


def read_meters_per_asset_unit(scene_dir: Path) -> float:
    path = scene_metadata_file(scene_dir)
    for row in _rows(path, ("parameter_name", "parameter_value")):
        if row["parameter_name"] == "meters_per_asset_unit":
            try:
                value = float(row["parameter_value"])
            except ValueError:
                value = float("nan")
            if not (np.isfinite(value) and value > 0):
                raise UslError(f"{path}: meters_per_asset_unit {row['parameter_value']!r} is not a positive number")
            return value
    raise UslError(f"{path}: no meters_per_asset_unit row")
