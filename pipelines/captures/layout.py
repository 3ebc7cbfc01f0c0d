"""Which folders are captures, and where each one's poses and frames come from.

A capture folder holds, in this order of preference, ``transforms.json`` (nerfstudio, instant-ngp,
Polycam, Record3D), a COLMAP model (``sparse/0`` or ``colmap/sparse/0``, images in ``images/``), or
only frames: an ``images/`` folder or one video file. ROOT is one capture itself, or each of its
sub-folders that is one becomes a scene named after the folder.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from usl.errors import UslError
from usl.records.names import check_name

from .colmap import IMAGES_DIR, find_model
from .transforms import TRANSFORMS
from .video import VIDEO_SUFFIXES

KINDS = ("transforms", "colmap", "images", "video")
WHAT = "transforms.json, sparse/0 or colmap/sparse/0, images/ or a video file"


@dataclass(frozen=True)
class CaptureSource:
    kind: str  # one of KINDS
    path: str  # transforms.json, the model folder, the images folder or the video file


def frame_source(folder: Path) -> CaptureSource | None:
    """The capture's frames without poses: ``images/``, else its one video file."""
    if (folder / IMAGES_DIR).is_dir():
        return CaptureSource("images", str(folder / IMAGES_DIR))
    videos = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in VIDEO_SUFFIXES)
    if len(videos) > 1:
        raise UslError(
            f"{folder}: {len(videos)} video files ({videos[0].name}, {videos[1].name}, ...); one per capture"
        )
    return CaptureSource("video", str(videos[0])) if videos else None


def posed_source(folder: Path) -> CaptureSource | None:
    if (folder / TRANSFORMS).is_file():
        return CaptureSource("transforms", str(folder / TRANSFORMS))
    model = find_model(folder)
    return CaptureSource("colmap", str(model)) if model is not None else None


def capture_source(folder: Path, sfm: bool) -> CaptureSource | None:
    """Where the capture in ``folder`` comes from (None: not a capture). ``sfm``: ignore given poses."""
    if not sfm:
        return posed_source(folder) or frame_source(folder)
    return frame_source(folder)


def find_captures(root: Path, sfm: bool) -> list[tuple[str, Path, CaptureSource]]:
    """(scene id, folder, source) of ROOT itself, or of every capture folder in it, by name."""
    if not root.is_dir():
        raise UslError(f"{root}: no such folder")
    found = capture_source(root, sfm)
    folders = [(root, found)] if found else [(p, capture_source(p, sfm)) for p in sorted(root.iterdir()) if p.is_dir()]
    captures = [(check_name(p.name, "capture name", str(p)), p, s) for p, s in folders if s is not None]
    if not captures:
        need = "images/ or a video file (--poses sfm)" if sfm else WHAT
        raise UslError(f"{root}: neither it nor a folder in it holds a capture ({need})")
    for _scene_id, folder, source in captures:
        if source.kind in ("images", "video") and not sfm:
            raise UslError(f"{folder}: frames without poses ({source.path}); pass --poses sfm to compute them")
    return captures
