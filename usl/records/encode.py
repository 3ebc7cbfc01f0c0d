"""Encoding and decoding of record fields: images, depth, masks (COCO RLE) and whole rows.

Every pipeline goes through these helpers so that boxes, areas and nearest depths are derived from
masks the same way everywhere (docs/design.md §2-3).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from pycocotools import mask as mask_utils

from usl.errors import UslError, one_line

DEPTH_SCALE = 1000.0  # depth PNG stores millimetres
MAX_DEPTH_MM = np.iinfo(np.uint16).max
_IMREAD_RGB = getattr(cv2, "IMREAD_COLOR_RGB", None)


def encode_image(rgb: np.ndarray, codec: str = "png", quality: int = 95) -> bytes:
    """Encode an RGB uint8 image as PNG or JPEG bytes."""
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"expected an (H, W, 3) uint8 image, got {rgb.dtype} {rgb.shape}")
    bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    if codec == "png":
        ok, buf = cv2.imencode(".png", bgr, [cv2.IMWRITE_PNG_COMPRESSION, 3])
    elif codec in ("jpeg", "jpg"):
        ok, buf = cv2.imencode(".jpg", bgr, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    else:
        raise ValueError(f"unknown image codec {codec!r} (png or jpeg)")
    if not ok:
        raise RuntimeError(f"OpenCV failed to encode a {rgb.shape} image as {codec}")
    return buf.tobytes()


def image_bytes(image: bytes | dict[str, Any], field: str = "image") -> bytes:
    """The encoded bytes of a frame's ``image`` or ``depth``: an Image struct ``{bytes, path}`` (image
    from v2, depth from v3) or the bytes themselves (earlier versions)."""
    if isinstance(image, dict):
        if image.get("bytes") is None:
            raise UslError(f"{field} struct has no embedded bytes (path {image.get('path')!r}); records embed them")
        return image["bytes"]
    return image


def decode_image(data: bytes | dict[str, Any]) -> np.ndarray:
    """Decode a frame's ``image`` (Image struct or PNG/JPEG bytes) to an (H, W, 3) RGB uint8 array."""
    data = image_bytes(data)
    if not data:
        raise UslError("image bytes are empty")
    buffer = np.frombuffer(data, np.uint8)
    if _IMREAD_RGB is not None:  # OpenCV >= 4.10 decodes straight to RGB, saving a full-image pass
        rgb = cv2.imdecode(buffer, _IMREAD_RGB)
    else:
        bgr = cv2.imdecode(buffer, cv2.IMREAD_COLOR)
        rgb = None if bgr is None else cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)
    if rgb is None:
        raise UslError("image bytes do not decode as PNG or JPEG")
    return rgb


def encode_depth(depth_m: np.ndarray) -> bytes:
    """Planar depth in metres -> 16-bit PNG of millimetres; NaN, inf and <= 0 become 0 (unknown).

    Depths beyond 65.535 m do not fit and also become 0 rather than wrapping around.
    """
    mm = np.rint(np.asarray(depth_m, dtype=np.float64) * DEPTH_SCALE)
    with np.errstate(invalid="ignore"):
        mm[~((mm > 0) & (mm <= MAX_DEPTH_MM))] = 0  # NaN compares False, so it is cleared too
    ok, buf = cv2.imencode(".png", mm.astype(np.uint16), [cv2.IMWRITE_PNG_COMPRESSION, 1])
    if not ok:
        raise RuntimeError("OpenCV failed to encode a depth PNG")
    return buf.tobytes()


def decode_depth(data: bytes | dict[str, Any]) -> np.ndarray:
    """A frame's ``depth`` (Image struct, or the 16-bit PNG bytes of millimetres) -> float32 metres
    with NaN where unknown."""
    data = image_bytes(data, "depth")
    if not data:
        raise UslError("depth bytes are empty")
    mm = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if mm is None or mm.dtype != np.uint16:
        raise UslError("depth bytes are not a 16-bit PNG")
    depth = mm.astype(np.float32) / DEPTH_SCALE
    depth[mm == 0] = np.nan
    return depth


def encode_mask(mask: np.ndarray) -> dict[str, Any]:
    """Boolean (H, W) mask -> COCO compressed RLE ``{"size": [H, W], "counts": str}``."""
    as_bytes = mask.view(np.uint8) if mask.dtype == bool else mask.astype(np.uint8)
    rle = mask_utils.encode(np.asfortranarray(as_bytes))
    return {"size": [int(rle["size"][0]), int(rle["size"][1])], "counts": rle["counts"].decode("ascii")}


def decode_mask(rle: dict[str, Any]) -> np.ndarray:
    """COCO RLE (as stored in records) -> boolean (H, W) mask."""
    try:
        counts = rle["counts"]
        height, width = (int(v) for v in rle["size"])
        coco = {"size": [height, width], "counts": counts.encode("ascii") if isinstance(counts, str) else counts}
        mask = mask_utils.decode(coco)
    except Exception as exc:  # pycocotools raises plain Exceptions (and TypeErrors) for bad RLE
        raise UslError(f"mask RLE does not decode ({one_line(exc)})") from exc
    return mask.astype(bool)


@contextmanager
def decoding(row: dict[str, Any], source: str = "") -> Iterator[None]:
    """Turn any failure to decode a row's fields into one line naming the shard, scene and view."""
    try:
        yield
    except Exception as exc:
        where = f"{source}: " if source else ""
        raise UslError(f"{where}scene {row.get('scene_id')!r} view {row.get('view_id')}: {one_line(exc)}") from exc


def mask_bbox(mask: np.ndarray) -> list[float]:
    """Tight box ``[x0, y0, x1, y1]`` around a non-empty mask in the pixel frame of docs/design.md §2.

    Pixel (row i, col j) covers [j, j+1] x [i, i+1], so the box spans whole pixels.
    """
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    return [float(cols[0]), float(rows[0]), float(cols[-1] + 1), float(rows[-1] + 1)]


def make_instance(
    instance_id: int, category_id: int, mask: np.ndarray, depth_m: np.ndarray | None = None
) -> dict[str, Any]:
    """One entry of a frame's ``instances`` list, all derived from its mask (and depth)."""
    mask = np.asarray(mask, dtype=bool)
    area = int(np.count_nonzero(mask))
    if area == 0:
        raise ValueError(f"instance {instance_id} has an empty mask")
    depth_min = float("nan")
    if depth_m is not None:
        values = depth_m[mask]
        values = values[np.isfinite(values) & (values > 0)]
        if values.size:
            depth_min = float(values.min())
    return {
        "instance_id": int(instance_id),
        "category_id": int(category_id),
        "mask": encode_mask(mask),
        "box_xyxy": mask_bbox(mask),
        "area": area,
        "depth_min": depth_min,
    }


def frame_row(
    scene_id: str,
    view_id: int,
    image: bytes,
    K: np.ndarray,
    cam_to_world: np.ndarray,
    instances: list[dict[str, Any]],
    height: int,
    width: int,
    depth: bytes | None = None,
) -> dict[str, Any]:
    """A frames-table row in the current schema; ``image`` is the encoded PNG/JPEG, ``depth`` the
    16-bit PNG of ``encode_depth``."""
    return {
        "scene_id": str(scene_id),
        "view_id": int(view_id),
        "image": {"bytes": image, "path": None},
        "height": int(height),
        "width": int(width),
        "K": np.asarray(K, dtype=np.float64).reshape(9).tolist(),
        "cam_to_world": np.asarray(cam_to_world, dtype=np.float64).reshape(16).tolist(),
        "depth": None if depth is None else {"bytes": depth, "path": None},
        "instances": instances,
    }


def object_row(
    scene_id: str, instance_id: int, category_id: int, source_id: str, vertices: np.ndarray, faces: np.ndarray
) -> dict[str, Any]:
    """An objects-table row (vertices in the world frame, metres)."""
    return {
        "scene_id": str(scene_id),
        "instance_id": int(instance_id),
        "category_id": int(category_id),
        "source_id": str(source_id),
        "vertices": np.asarray(vertices, dtype=np.float32).reshape(-1, 3),
        "faces": np.asarray(faces, dtype=np.int32).reshape(-1, 3),
    }


def frame_K(row: dict[str, Any]) -> np.ndarray:
    return np.asarray(row["K"], dtype=np.float64).reshape(3, 3)


def frame_pose(row: dict[str, Any]) -> np.ndarray:
    return np.asarray(row["cam_to_world"], dtype=np.float64).reshape(4, 4)


def object_mesh(row: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (N, 3) float32, faces (M, 3) int32) of an objects-table row as read back."""
    verts = np.asarray(row["vertices"], dtype=np.float32).reshape(-1, 3)
    faces = np.asarray(row["faces"], dtype=np.int32).reshape(-1, 3)
    return verts, faces


@dataclass
class Skip:
    """Something a pipeline could not convert, kept in the manifest so nothing vanishes silently."""

    reason: str
    path: str = ""
    count: int = 1


@dataclass
class SceneRecord:
    """Everything one scene contributes to a shard.

    Frame rows are in ``frames``, or, for a long scene a worker streamed to disk (``FrameSink``), in
    the Parquet file ``frames_file``: then they never travel between processes or sit whole in memory.
    """

    scene_id: str
    frames: list[dict[str, Any]]
    objects: list[dict[str, Any]] = field(default_factory=list)
    skips: list[Skip] = field(default_factory=list)
    frames_file: Path | None = None
    # facts about how the scene was made that no frame row holds (e.g. where a capture's poses and
    # metric scale came from), JSON-able; the manifest keeps them per scene
    provenance: dict[str, Any] = field(default_factory=dict)
