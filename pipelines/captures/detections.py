"""Mask source: ``<capture>/detections.json``, COCO results as ``usl-segment`` (or detectron2) writes them.

Each detection names its image by ``file_name``: the frame whose path relative to the capture
ends the file name (``images/frame_00012.jpg``, ``/home/me/kitchen/images/frame_00012.jpg``), or
the one frame with that file name when the name alone is unique. Masks are compressed RLE at the
image's own size; frames remapped onto the capture's reference camera get their masks remapped the
same way. COCO categories outside the dataset spec are dropped here, unconfident detections by the
tracker's ``--min-score``.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np
from pycocotools import mask as mask_utils

from pipelines.scannet.detections_file import ScanDetections, checked_coco_id, checked_score, load_json
from pipelines.scannet.masks import Detection, checked_rle
from usl.errors import UslError

from .capture import Capture

DETECTIONS = "detections.json"


def _parts(name: str) -> tuple[str, ...]:
    return PurePosixPath(name.replace("\\", "/")).parts


class FrameNames:
    """file_name -> frame name of a capture: by path suffix, else by a unique base name."""

    def __init__(self, names: list[str]):
        self.by_base: dict[str, list[str]] = defaultdict(list)
        for name in names:
            self.by_base[_parts(name)[-1]].append(name)

    def match(self, file_name: str) -> str | None:
        parts = _parts(file_name)
        candidates = self.by_base.get(parts[-1], []) if parts else []
        if len(candidates) == 1:
            return candidates[0]
        suffix = [c for c in candidates if parts[-len(_parts(c)) :] == _parts(c)]
        return suffix[0] if len(suffix) == 1 else None


@dataclass(frozen=True)
class CaptureDetectionsSource:
    coco_to_category: tuple[tuple[int, int], ...]  # (COCO id, dataset category id)
    contiguous_ids: bool = False

    def open_scan(self, capture: Capture) -> ScanDetections:
        path = Path(capture.path) / DETECTIONS
        if not path.is_file():
            raise UslError(f"{path}: no such file (run usl-segment on the frames, or pass --masks model)")
        data = load_json(path)
        if not isinstance(data, list):
            raise UslError(f"{path}: not a COCO results list (usl-segment's output)")
        names = FrameNames(capture.image_names)
        index_of = {frame.name: index for index, frame in capture.frames.items()}
        mapping = dict(self.coco_to_category)
        by_frame: dict[int, list[Detection]] = defaultdict(list)
        for k, det in enumerate(data):
            if not isinstance(det, dict) or not isinstance(det.get("file_name"), str):
                raise UslError(f"{path}: detection {k} is not an object with a file_name")
            where = f"{path}: detection {k} ({det['file_name']})"
            name = names.match(det["file_name"])
            if name is None:
                raise UslError(f"{where}: names no frame of {capture.path} (or more than one)")
            score = checked_score(det.get("score"), where)
            category = mapping.get(checked_coco_id(det.get("category_id"), self.contiguous_ids, where))
            index = index_of.get(name)
            if category is None or index is None:  # another category, or a frame without a pose
                continue
            camera = capture.frames[index].camera
            try:
                rle = checked_rle(det.get("segmentation"), camera.height, camera.width)
            except ValueError as exc:
                raise UslError(f"{where}: malformed mask: {exc}") from None
            if not capture.rectifier(index).identity:
                mask = capture.rectify_mask(index, mask_utils.decode(rle))
                rle = mask_utils.encode(np.asfortranarray(mask))
            by_frame[index].append(Detection(category, score, rle))
        return ScanDetections(dict(by_frame))
