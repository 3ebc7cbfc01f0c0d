"""Synthetic Hypersim scenes in the released on-disk layout, with analytic ground truth.

A scene is a room of axis-aligned boxes in *asset units* (walls, floor, ceiling as slabs, a gap in
one wall through which rays see nothing, furniture inside). Frames are ray-cast exactly as Hypersim
casts them (``d_world = R_world_from_cam @ M_cam_from_uv @ [u, v, 1]``, README and
contrib/mikeroberts3000), so the truth (3D hit points, Euclidean distance, planar depth, labels)
never goes through the converter's K or depth formulas. Files follow the real dtypes: float16
colour and distance with NaN where there is no geometry, int16 labels with -1 for none, gzip HDF5
with one ``dataset`` each; or renderer EXRs for the EXR layout.

Reusable: ``make_scene`` / ``render`` / ``write_scene`` / ``write_split_csv`` / ``write_camera_csv``.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import h5py
import numpy as np
import OpenEXR

# A tilt-shift camera: off-centre principal point and a non-[0, 0, -1] third row, like ai_037_002.
TILT_SHIFT_M = np.array([[0.5796, 0.0, -0.0696], [0.0, 0.4347, 0.0927], [0.0, 0.0041, -1.0039]])
CANONICAL_M = np.array([[np.tan(np.pi / 6), 0.0, 0.0], [0.0, np.tan(np.pi / 6) * 0.75, 0.0], [0.0, 0.0, -1.0]])
BACKGROUND_RGB = (0.05, 0.07, 0.1)  # what Hypersim's colour images show where there is no geometry


@dataclass(frozen=True)
class Box:
    lo: tuple[float, float, float]  # asset units
    hi: tuple[float, float, float]
    instance_id: int  # semantic_instance id, -1: none
    semantic: int  # NYU40 id, -1: unlabelled
    entity_id: int  # render entity id >= 1
    albedo: tuple[float, float, float]


@dataclass(frozen=True)
class Keyframe:
    position: np.ndarray  # (3,) asset units
    orientation: np.ndarray  # (3, 3) R_world_from_cam, Hypersim camera axes (y up, looks down -z)


@dataclass
class SyntheticScene:
    name: str
    meters_per_asset_unit: float
    m_cam_from_uv: np.ndarray
    width: int
    height: int
    boxes: list[Box]
    trajectories: dict[str, list[Keyframe]] = field(default_factory=dict)


def _look_at(position: np.ndarray, target: np.ndarray, roll: float) -> np.ndarray:
    forward = (target - position) / np.linalg.norm(target - position)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    c, s = np.cos(roll), np.sin(roll)
    right, up = c * right + s * up, -s * right + c * up
    return np.stack([right, up, -forward], axis=1)


def room_boxes(scale: float) -> list[Box]:
    """A 4 x 3 x 2.5 m room (in asset units of ``scale`` m) with a window gap and furniture."""
    s = 1.0 / scale
    w, d, h, t = 2.0 * s, 1.5 * s, 2.5 * s, 0.1 * s
    return [
        Box((-w - t, -d - t, -t), (w + t, d + t, 0.0), 101, 2, 1, (0.5, 0.45, 0.4)),  # floor
        Box((-w - t, -d - t, h), (w + t, d + t, h + t), 102, 22, 2, (0.9, 0.9, 0.9)),  # ceiling
        Box((-w - t, -d - t, 0.0), (-w, d + t, h), 103, 1, 3, (0.7, 0.7, 0.6)),  # wall x-
        Box((-w, -d - t, 0.0), (w, -d, h), 104, 1, 4, (0.6, 0.7, 0.7)),  # wall y-
        Box((-w, d, 0.0), (w, d + t, h), 105, 1, 5, (0.7, 0.6, 0.7)),  # wall y+
        Box((w, -d - t, 0.0), (w + t, d + t, 0.8 * s), 106, 1, 6, (0.7, 0.7, 0.7)),  # wall x+ below the gap
        Box((0.6 * s, 0.3 * s, 0.0), (1.4 * s, 1.2 * s, 0.75 * s), 7, 7, 7, (0.6, 0.3, 0.1)),  # table
        # a box of "otherprop" on the table, but part of the table's instance
        Box((0.9 * s, 0.6 * s, 0.75 * s), (1.1 * s, 0.8 * s, 0.95 * s), 7, 40, 8, (0.2, 0.2, 0.8)),
        Box((0.0, -1.3 * s, 0.0), (0.8 * s, -0.5 * s, 0.9 * s), 11, 6, 9, (0.2, 0.5, 0.2)),  # sofa
        Box((0.1 * s, 0.7 * s, 0.0), (0.4 * s, 1.0 * s, 0.5 * s), 12, -1, 10, (0.8, 0.8, 0.1)),  # unlabelled
        Box((-0.05 * s, -0.3 * s, 1.2 * s), (0.05 * s, -0.2 * s, 1.3 * s), 13, 35, 11, (1.0, 0.9, 0.5)),  # tiny lamp
    ]


def make_scene(
    name: str = "ai_001_001",
    width: int = 64,
    height: int = 48,
    tilt_shift: bool = True,
    meters_per_asset_unit: float = 0.0254,
    cameras: tuple[str, ...] = ("cam_00",),
    keyframes: int = 8,
) -> SyntheticScene:
    """A room scene; each camera walks a short arc at eye height with a little roll."""
    s = 1.0 / meters_per_asset_unit
    scene = SyntheticScene(
        name,
        meters_per_asset_unit,
        TILT_SHIFT_M if tilt_shift else CANONICAL_M,
        width,
        height,
        room_boxes(meters_per_asset_unit),
    )
    for c, camera in enumerate(cameras):
        frames = []
        for k in range(keyframes):
            angle = 0.35 * c + 0.12 * k
            position = np.array([-1.2 + 0.6 * np.cos(angle), -0.2 + 0.5 * np.sin(angle), 1.4 + 0.05 * k]) * s
            target = np.array([1.0, 0.5 - 0.3 * c, 0.6 + 0.4 * np.sin(angle)]) * s
            frames.append(Keyframe(position, _look_at(position, target, roll=0.03 * np.sin(3 * angle))))
        scene.trajectories[camera] = frames
    return scene


@dataclass
class FrameTruth:
    points: np.ndarray  # (H, W, 3) world hit points in metres, NaN: no geometry
    distance: np.ndarray  # (H, W) metres to the camera centre
    planar: np.ndarray  # (H, W) camera-frame depth in metres
    instance: np.ndarray  # (H, W) int16
    semantic: np.ndarray  # (H, W) int16
    entity: np.ndarray  # (H, W) int16, -1: none
    rgb: np.ndarray  # (H, W, 3) float32 linear radiance
    face: np.ndarray  # (H, W) which face of which box was hit (6 * box + 2 * axis + side), -1: none
    position: np.ndarray  # (H, W, 3) float32 hit points in asset units (EXR VRayPosition)


def render(
    scene: SyntheticScene, camera: str, frame: int, width: int | None = None, height: int | None = None
) -> FrameTruth:
    """Ray-cast one keyframe at ``width`` x ``height`` (default: the scene's size)."""
    width, height = width or scene.width, height or scene.height
    key = scene.trajectories[camera][frame]
    u = -1.0 + (2.0 * np.arange(width) + 1.0) / width
    v = 1.0 - (2.0 * np.arange(height) + 1.0) / height
    uv = np.stack(np.broadcast_arrays(u[None, :], v[:, None], 1.0), axis=-1).reshape(-1, 3)
    rays = uv @ (key.orientation @ scene.m_cam_from_uv).T
    best_t = np.full(len(rays), np.inf)
    best_box = np.full(len(rays), -1)
    best_face = np.full(len(rays), -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        for b, box in enumerate(scene.boxes):
            t1 = (np.asarray(box.lo) - key.position) / rays
            t2 = (np.asarray(box.hi) - key.position) / rays
            entry = np.minimum(t1, t2)
            near = entry.max(axis=1)
            far = np.maximum(t1, t2).min(axis=1)
            hit = (near <= far) & (near > 0) & (near < best_t)
            axis = entry.argmax(axis=1)
            face = 6 * b + 2 * axis + (t1[np.arange(len(rays)), axis] > t2[np.arange(len(rays)), axis])
            best_t[hit], best_box[hit], best_face[hit] = near[hit], b, face[hit]
    valid = best_box >= 0
    t = np.where(valid, best_t, np.nan)
    position = key.position + t[:, None] * rays
    offsets = position - key.position
    distance = np.linalg.norm(offsets, axis=1) * scene.meters_per_asset_unit
    planar = -(offsets @ key.orientation)[:, 2] * scene.meters_per_asset_unit

    def per_box(attribute: str, none: int) -> np.ndarray:
        table = np.array([getattr(b, attribute) for b in scene.boxes] + [none], dtype=np.int16)
        return table[best_box].reshape(height, width)

    albedo = np.array([b.albedo for b in scene.boxes] + [BACKGROUND_RGB], dtype=np.float64)[best_box]
    shade = 1.5 + 0.5 * np.sin(position[:, 0] * scene.meters_per_asset_unit * 7.0)
    rgb = np.where(valid[:, None], albedo * np.nan_to_num(shade)[:, None] * 2.0, albedo)
    return FrameTruth(
        points=(position * scene.meters_per_asset_unit).reshape(height, width, 3),
        distance=distance.reshape(height, width),
        planar=planar.reshape(height, width),
        instance=per_box("instance_id", -1),
        semantic=per_box("semantic", -1),
        entity=per_box("entity_id", -1),
        rgb=rgb.reshape(height, width, 3).astype(np.float32),
        face=best_face.reshape(height, width),
        position=position.reshape(height, width, 3).astype(np.float32),
    )


def write_hdf5(path: Path, data: np.ndarray, compression: int | None = 9) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with h5py.File(path, "w") as f:
        if compression is None:
            f.create_dataset("dataset", data=data)
        else:
            f.create_dataset("dataset", data=data, compression="gzip", compression_opts=compression)


def write_exr(path: Path, channels: dict[str, np.ndarray]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {k: np.ascontiguousarray(v) for k, v in channels.items()}) as exr:
        exr.write(str(path))


def write_scene(
    root: Path, scene: SyntheticScene, frames: dict[str, list[int]], exr: bool = False, compression: int | None = 9
) -> Path:
    """Write ``scene`` under ``root/<name>``: metadata, keyframes, and the listed frames' images."""
    scene_dir = Path(root) / scene.name
    detail = scene_dir / "_detail"
    detail.mkdir(parents=True, exist_ok=True)
    (detail / "metadata_scene.csv").write_text(
        f"parameter_name,parameter_value\nmeters_per_asset_unit,{scene.meters_per_asset_unit!r}\n"
    )
    (detail / "metadata_cameras.csv").write_text("camera_name\n" + "".join(f"{c}\n" for c in scene.trajectories))
    for camera, keyframes in scene.trajectories.items():
        write_hdf5(detail / camera / "camera_keyframe_positions.hdf5", np.stack([k.position for k in keyframes]))
        write_hdf5(detail / camera / "camera_keyframe_orientations.hdf5", np.stack([k.orientation for k in keyframes]))
        write_hdf5(detail / camera / "camera_keyframe_frame_indices.hdf5", np.arange(len(keyframes)))
        images = scene_dir / "images"
        for frame in frames.get(camera, []):
            truth = render(scene, camera, frame)
            name = f"frame.{frame:04d}"
            geometry = images / f"scene_{camera}_geometry_hdf5"
            write_hdf5(geometry / f"{name}.semantic.hdf5", truth.semantic, compression)
            write_hdf5(geometry / f"{name}.semantic_instance.hdf5", truth.instance, compression)
            if exr:
                write_exr(
                    images / f"scene_{camera}_final" / f"{name}.exr",
                    {c: truth.rgb[..., k] for k, c in enumerate("RGB")},
                )
                entity = truth.entity.astype(np.float32)
                entity[entity < 0] = 0.0  # V-Ray writes 0 where no entity was hit
                channels = {"VRayRenderEntityID": entity}
                channels.update({f"VRayPosition.{c}": truth.position[..., k] for k, c in enumerate("RGB")})
                write_exr(images / f"scene_{camera}_geometry" / f"{name}.exr", channels)
                continue
            write_hdf5(
                images / f"scene_{camera}_final_hdf5" / f"{name}.color.hdf5", truth.rgb.astype(np.float16), compression
            )
            write_hdf5(geometry / f"{name}.depth_meters.hdf5", truth.distance.astype(np.float16), compression)
            write_hdf5(geometry / f"{name}.render_entity_id.hdf5", truth.entity, compression)
    return scene_dir


SPLIT_HEADER = [
    "scene_name",
    "camera_name",
    "frame_id",
    "included_in_public_release",
    "exclude_reason",
    "split_partition_name",
]


def split_rows(
    scene: str, camera: str, frames: range | list[int], split: str, excluded: dict[int, str] | None = None
) -> list[list[str]]:
    """Split-CSV rows of one trajectory; ``excluded`` maps frame -> exclude_reason."""
    excluded = excluded or {}
    return [
        [
            scene,
            camera,
            str(f),
            "False" if f in excluded else "True",
            excluded.get(f, ""),
            "" if f in excluded else split,
        ]
        for f in frames
    ]


def write_split_csv(path: Path, rows: list[list[str]]) -> Path:
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(SPLIT_HEADER)
        writer.writerows(rows)
    return path


def write_camera_csv(path: Path, scenes: list[SyntheticScene]) -> Path:
    """Columns as in contrib/mikeroberts3000/metadata_camera_parameters.csv (the ones we read, and a
    few we do not, to show extra columns are tolerated)."""
    m_columns = [f"M_cam_from_uv_{i}{j}" for i in range(3) for j in range(3)]
    header = [
        "scene_name",
        "settings_output_img_height",
        "settings_output_img_width",
        "settings_units_info_meters_scale",
        "use_camera_physical",
        *m_columns,
    ]
    with open(path, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(header)
        for s in scenes:
            writer.writerow(
                [
                    s.name,
                    float(s.height),
                    float(s.width),
                    s.meters_per_asset_unit,
                    "False",
                    *s.m_cam_from_uv.reshape(-1).tolist(),
                ]
            )
    return path


def truncate(path: Path, keep: float = 0.5) -> None:
    """Cut a file short, as an interrupted download does."""
    data = Path(path).read_bytes()
    Path(path).write_bytes(data[: int(len(data) * keep)])


def edit_hdf5(path: Path, edit) -> None:
    """Rewrite one HDF5 ``dataset`` with ``edit(array) -> array`` (same compression as the release)."""
    with h5py.File(path, "r") as f:
        data = f["dataset"][()]
    write_hdf5(Path(path), edit(data))
