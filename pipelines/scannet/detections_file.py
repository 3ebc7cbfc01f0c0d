"""Mask source (1): detections in the COCO results format that detectron2 writes.

Users run PointRend (or any instance segmenter) on exported ScanNet colour frames elsewhere and
bring two files:

* results JSON(s): a list of ``{"image_id", "category_id", "score", "segmentation": {"size": [H, W],
  "counts": str}, "bbox"}`` as detectron2's ``COCOEvaluator`` saves (``coco_instances_results.json``).
  ``category_id`` is a COCO id (1..90), or with ``contiguous_ids`` detectron2's 0-based class index.
* an images JSON mapping ``image_id`` to frames: COCO's ``images`` list (or a COCO dataset dict with
  an ``images`` key, i.e. the file registered with detectron2 to run inference), each
  ``{"id", "file_name", "width", "height"}`` where ``file_name`` has the scan id as a folder and the
  frame index as the file stem: ``scene0000_00/color/123.jpg`` (any prefix before the scan id).

Masks must be at the colour resolution of the scan (e.g. 1296x968). The main process splits the
results by scan into a temporary folder (one JSON-lines file per scan), so build workers read only
their scan's detections and never the whole file.
"""

from __future__ import annotations

import json
import math
import re
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from data_specs import coco_category_ids
from usl.errors import UslError

from .masks import Detection, FrameView, ScanInfo, checked_rle

FILE_NAME = re.compile(r"(?:^|[\\/])(scene\d{4}_\d{2})[\\/](?:.*[\\/])?(\d+)\.(?:jpe?g|png)$", re.IGNORECASE)
SOURCES_FILE = "sources.json"


@dataclass(frozen=True)
class ImageEntry:
    scene_id: str
    frame: int
    width: int
    height: int


def frame_of_file_name(file_name: str) -> tuple[str, int] | None:
    """(scan id, frame index) from ``.../sceneXXXX_YY/<anything>/<frame>.jpg``, None if it does not fit."""
    match = FILE_NAME.search(file_name)
    return (match.group(1), int(match.group(2))) if match else None


def load_json(path: Path) -> Any:
    """A JSON file, or a one-line UslError naming it."""
    try:
        with open(path, "rb") as f:
            return json.load(f)
    except OSError as exc:
        raise UslError(f"{path}: cannot read ({exc.strerror})") from None
    except json.JSONDecodeError as exc:
        raise UslError(f"{path}: not valid JSON ({exc})") from None


def load_images(path: Path) -> dict[int, ImageEntry]:
    data = load_json(path)
    images = data.get("images") if isinstance(data, dict) else data
    if not isinstance(images, list):
        raise UslError(f"{path}: expected COCO's images list (or a dict with an 'images' key)")
    entries = {}
    for image in images:
        try:
            image_id, name, width, height = image["id"], image["file_name"], int(image["width"]), int(image["height"])
        except (KeyError, TypeError, ValueError):
            raise UslError(f"{path}: image entry {image!r} lacks id, file_name, width or height") from None
        where = frame_of_file_name(str(name))
        if where is None:
            raise UslError(
                f"{path}: image {image_id}: cannot tell scan and frame from file_name {name!r} "
                "(expected .../sceneXXXX_YY/.../<frame index>.jpg)"
            )
        if image_id in entries:
            raise UslError(f"{path}: image id {image_id} appears twice")
        entries[image_id] = ImageEntry(where[0], where[1], width, height)
    return entries


def split_detections(results: Iterable[Path], images_path: Path, scene_ids: set[str], out_dir: Path) -> None:
    """Write ``<out_dir>/<scan>.jsonl`` with the detections of each scan in ``scene_ids``.

    Results files are read one at a time, so memory is bounded by the largest one; pass several
    (e.g. one per scan or per chunk) for collections too large to parse at once.
    """
    images = load_images(images_path)
    results = [Path(p) for p in results]
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / SOURCES_FILE).write_text(json.dumps({"results": [str(p) for p in results], "images": str(images_path)}))
    for src, path in enumerate(results):
        data = load_json(path)
        if not isinstance(data, list):
            raise UslError(f"{path}: expected a list of detections (COCO results format)")
        per_scene: dict[str, list[str]] = defaultdict(list)
        for k, det in enumerate(data):
            if not isinstance(det, dict) or "image_id" not in det:
                raise UslError(f"{path}: detection {k} is not an object with an image_id")
            image = images.get(det["image_id"])
            if image is None:
                raise UslError(
                    f"{path}: detection {k} refers to image_id {det['image_id']!r}, which {images_path} does not list"
                )
            if image.scene_id not in scene_ids:
                continue
            line = {
                "src": src,
                "image_id": det["image_id"],
                "frame": image.frame,
                "width": image.width,
                "height": image.height,
                "category_id": det.get("category_id"),
                "score": det.get("score"),
                "segmentation": det.get("segmentation"),
            }
            per_scene[image.scene_id].append(json.dumps(line))
        for scene_id, lines in per_scene.items():
            with open(out_dir / f"{scene_id}.jsonl", "a") as f:
                f.write("\n".join(lines) + "\n")


def checked_coco_id(category_id: Any, contiguous: bool, where: str) -> int:
    """A detection's COCO category id (from detectron2's 0-based class index when ``contiguous``)."""
    if not isinstance(category_id, int):
        raise UslError(f"{where}: category_id {category_id!r} is not an integer")
    if contiguous:
        if not 0 <= category_id < len(coco_category_ids()):
            raise UslError(f"{where}: contiguous category index {category_id} is outside 0..79")
        return coco_category_ids()[category_id]
    if category_id not in coco_category_ids():
        hint = " (0-based class indices? use --category-ids contiguous)" if category_id == 0 else ""
        raise UslError(f"{where}: category_id {category_id} is not a COCO category id{hint}")
    return category_id


def checked_score(score: Any, where: str) -> float:
    if not isinstance(score, (int, float)) or not math.isfinite(score):
        raise UslError(f"{where}: score {score!r} is not a finite number")
    return float(score)


@dataclass(frozen=True)
class DetectionsFileSource:
    """Opens the per-scan detections that ``split_detections`` wrote to ``cache_dir``."""

    cache_dir: str
    coco_to_category: tuple[tuple[int, int], ...]  # (COCO id, dataset category id)
    contiguous_ids: bool = False

    def open_scan(self, scan: ScanInfo) -> ScanDetections:
        cache = Path(self.cache_dir)
        sources = json.loads((cache / SOURCES_FILE).read_text())["results"]
        path = cache / f"{scan.scene_id}.jsonl"
        by_frame: dict[int, list[Detection]] = defaultdict(list)
        if path.exists():
            mapping = dict(self.coco_to_category)
            frames = set(scan.frame_indices)
            with open(path) as f:
                for text in f:
                    line = json.loads(text)
                    detection = self._detection(line, sources[line["src"]], scan, frames, mapping)
                    if detection is not None:
                        by_frame[line["frame"]].append(detection)
        return ScanDetections(dict(by_frame))

    def _detection(
        self, line: dict[str, Any], source: str, scan: ScanInfo, frames: set[int], mapping: dict[int, int]
    ) -> Detection | None:
        where = f"{source}: image_id {line['image_id']!r}"
        width, height = scan.color_size
        if (line["width"], line["height"]) != (width, height):
            raise UslError(
                f"{source}: detections for {scan.scene_id} are for {line['width']}x{line['height']} "
                f"images, but {scan.path} has {width}x{height} colour frames"
            )
        if line["frame"] not in frames:
            raise UslError(f"{where} names frame {line['frame']} of {scan.scene_id}, which {scan.path} does not have")
        coco_id = checked_coco_id(line["category_id"], self.contiguous_ids, where)
        score = checked_score(line["score"], where)
        try:
            rle = checked_rle(line["segmentation"], height, width)
        except ValueError as exc:
            raise UslError(f"{where}: malformed mask: {exc}") from None
        category = mapping.get(coco_id)
        return None if category is None else Detection(category, score, rle)


class ScanDetections:
    def __init__(self, by_frame: dict[int, list[Detection]]):
        self.by_frame = by_frame

    def detect(self, frame: FrameView) -> list[Detection]:
        return self.by_frame.get(frame.index, [])
