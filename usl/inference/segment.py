"""Instance segmentation of image files into COCO results JSON (what ``usl-segment`` writes).

Each result is detectron2's ``instances_to_coco_json`` entry: ``image_id``, ``category_id`` (a COCO
id), ``bbox`` (x, y, width, height in pixels), ``score`` and ``segmentation`` (compressed RLE with
string counts), plus the image's ``file_name`` so the file needs no separate image list.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from pycocotools import mask as mask_utils
from tqdm import tqdm

from usl.errors import UslError
from usl.model.segmenter import InstanceSegmenter, Segmentation


def read_rgb(path: str | Path) -> np.ndarray:
    """An image file as RGB uint8 (H, W, 3), EXIF orientation applied (as detectron2 reads it)."""
    image = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if image is None:
        raise UslError(f"{path}: not a readable image file")
    return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def encode_masks(masks: np.ndarray) -> list[dict[str, Any]]:
    """(K, H, W) bool masks as COCO RLE with ``counts`` as text (JSON-ready)."""
    if not len(masks):
        return []
    rles = mask_utils.encode(np.asfortranarray(masks.transpose(1, 2, 0).astype(np.uint8)))
    return [{"size": [int(s) for s in rle["size"]], "counts": rle["counts"].decode("ascii")} for rle in rles]


def coco_results(segmentation: Segmentation, image_id: int, file_name: str) -> list[dict[str, Any]]:
    """One image's instances as COCO results entries, best first."""
    boxes = segmentation.boxes.astype(np.float64)
    xywh = np.concatenate([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]], axis=1)
    return [
        {
            "image_id": image_id,
            "file_name": file_name,
            "category_id": int(category),
            "bbox": [float(v) for v in box],
            "score": float(score),
            "segmentation": rle,
        }
        for category, box, score, rle in zip(
            segmentation.category_ids, xywh, segmentation.scores, encode_masks(segmentation.masks), strict=True
        )
    ]


def segment_files(
    segmenter: InstanceSegmenter, paths: Sequence[str | Path], batch_size: int = 1, progress: bool = False
) -> Iterator[tuple[int, Path, Segmentation]]:
    """``(index, path, segmentation)`` per image file, in order, ``batch_size`` images per forward pass."""
    if batch_size < 1:
        raise UslError(f"batch size must be >= 1, got {batch_size}")
    bar = tqdm(total=len(paths), desc="segmenting", unit="image", disable=not progress)
    try:
        for start in range(0, len(paths), batch_size):
            batch = [Path(p) for p in paths[start : start + batch_size]]
            for offset, (path, result) in enumerate(zip(batch, segmenter([read_rgb(p) for p in batch]), strict=True)):
                yield start + offset, path, result
            bar.update(len(batch))
    finally:
        bar.close()
