"""Mask source (2): ScanNet's own 2D instance labels, whose ids are consistent across a scan's frames.

Per frame, ``instance-filt/{i}.png`` (uint8, 0 = no instance) gives the instances and
``label-filt/{i}.png`` (uint16 ScanNet label ids) their labels; both live beside the scan as
folders or as the downloaded ``<scan>_2d-instance-filt.zip`` / ``<scan>_2d-label-filt.zip``.
An instance's label is the most common label under its mask, mapped to a dataset category through
``scannetv2-labels.combined.tsv``: its ``category`` column, else its ``nyu40class``, matched by name
(with the aliases below for names COCO spells differently). The instance value becomes the
detection's ``source_id``: the truth the IoU tracker is measured against, or the tracks themselves.
"""

from __future__ import annotations

import csv
import zipfile
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from pycocotools import mask as mask_utils

from usl.errors import UslError

from .masks import Detection, FrameView, ScanInfo

NAME_ALIASES = {
    "sofa": "couch",
    "plant": "potted plant",
    "table": "dining table",
    "television": "tv",
    "refridgerator": "refrigerator",
    "mini fridge": "refrigerator",
    "books": "book",
}


def label_categories(tsv: Path, categories: tuple[tuple[int, str], ...]) -> dict[int, int]:
    """ScanNet label id -> dataset category id, for the labels that name one of ``categories``."""
    by_name = {name.lower(): cid for cid, name in categories}
    try:
        with open(tsv, newline="") as f:
            rows = list(csv.DictReader(f, delimiter="\t"))
    except OSError as exc:
        raise UslError(f"{tsv}: cannot read ({exc.strerror})") from None
    if not rows or not {"id", "category", "nyu40class"} <= set(rows[0]):
        raise UslError(f"{tsv}: expected ScanNet's label table with id, category and nyu40class columns")
    mapping = {}
    for row in rows:
        for name in (row["category"], row["nyu40class"]):
            name = (name or "").strip().lower()
            name = NAME_ALIASES.get(name, name)
            if name in by_name:
                mapping[int(row["id"])] = by_name[name]
                break
    return mapping


class _ImageSet:
    """``<kind>/{i}.png`` from a folder or from the downloaded zip, read one image at a time."""

    def __init__(self, scan_dir: Path, scene_id: str, kind: str):
        self.folder = scan_dir / kind
        self.zip_path = scan_dir / f"{scene_id}_2d-{kind}.zip"
        self._zip: zipfile.ZipFile | None = None
        if not self.folder.is_dir():
            if not self.zip_path.is_file():
                raise UslError(f"{scan_dir}: neither a {kind}/ folder nor {self.zip_path.name}")
            self._zip = zipfile.ZipFile(self.zip_path)
            self._names = set(self._zip.namelist())

    def read(self, index: int, dtype: type) -> np.ndarray | None:
        member = f"{self.folder.name}/{index}.png"
        if self._zip is None:
            path = self.folder / f"{index}.png"
            source = path
            data = path.read_bytes() if path.is_file() else None
        else:
            source = f"{self.zip_path}:{member}"
            data = self._zip.read(member) if member in self._names else None
        if data is None:
            return None
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None or image.ndim != 2 or image.dtype != dtype:
            raise UslError(f"{source}: expected a single-channel {np.dtype(dtype).name} PNG")
        return image


@dataclass(frozen=True)
class ScanNetLabelsSource:
    label_map: str  # scannetv2-labels.combined.tsv
    categories: tuple[tuple[int, str], ...]  # (dataset category id, name)

    def open_scan(self, scan: ScanInfo) -> ScanLabels:
        path = Path(scan.path)
        scan_dir = path if path.is_dir() else path.parent
        return ScanLabels(
            _ImageSet(scan_dir, scan.scene_id, "instance-filt"),
            _ImageSet(scan_dir, scan.scene_id, "label-filt"),
            label_categories(Path(self.label_map), self.categories),
        )


class ScanLabels:
    def __init__(self, instances: _ImageSet, labels: _ImageSet, categories: dict[int, int]):
        self.instances, self.labels, self.categories = instances, labels, categories

    def detect(self, frame: FrameView) -> list[Detection]:
        instance = self.instances.read(frame.index, np.uint8)
        label = self.labels.read(frame.index, np.uint16)
        if instance is None or label is None:
            return []
        if instance.shape != label.shape:
            raise UslError(
                f"{self.instances.folder.parent}: frame {frame.index}: instance-filt "
                f"{instance.shape} and label-filt {label.shape} differ in size"
            )
        detections = []
        for value in np.unique(instance):
            if value == 0:
                continue
            mask = instance == value
            labels, counts = np.unique(label[mask], return_counts=True)
            category = self.categories.get(int(labels[np.argmax(counts)]))
            if category is not None:
                rle = mask_utils.encode(np.asfortranarray(mask.astype(np.uint8)))
                detections.append(Detection(category, 1.0, rle, source_id=int(value)))
        return detections
