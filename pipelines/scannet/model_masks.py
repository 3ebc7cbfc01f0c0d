"""Mask source (3): usl's own COCO instance segmenter (``usl-segment``'s) run on the scan's colour frames.

The first time a scan is opened, the build worker segments its processed (strided) colour frames
and writes the detections the build keeps (a ScanNet category, score >= ``--min-score``) to
``<out>/.build/segments/<scan>.json``. That folder belongs to the build, not to one run: every run
on the same ``--out`` (a resumed build, or several machines sharing the folder) reads a finished
scan's detections from there and never segments it again. The build fingerprint holds the weights
file and the segmenter options, so a cached file always comes from this build's segmenter.

Categories are handled as for ``--masks detections``: COCO ids map to the dataset's categories
through data_specs/scannet.yaml's ``coco_id``; detections of other COCO categories are dropped.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from usl.errors import UslError
from usl.records.atomic import write_json_atomic
from usl.records.build_state import STATE_DIR

from .detections_file import ScanDetections
from .masks import Detection, ScanInfo

if TYPE_CHECKING:
    from usl.model.segmenter import InstanceSegmenter, SegmenterConfig

CACHE_FORMAT = 1


def segments_dir(out: Path) -> Path:
    """The per-scan detections of a ``--masks model`` build: inside the build's state folder."""
    return Path(out) / STATE_DIR / "segments"


class ColorScan(ScanInfo, Protocol):
    def color(self, index: int) -> np.ndarray: ...


@lru_cache(maxsize=1)
def _segmenter(weights: str, cfg: SegmenterConfig, device: str) -> InstanceSegmenter:
    """One segmenter per worker process, loaded when its first scan needs it."""
    from usl.model.pretrained import WeightsError
    from usl.model.segmenter import InstanceSegmenter

    try:
        return InstanceSegmenter.from_weights(weights, cfg, device)
    except WeightsError as exc:
        raise UslError(str(exc)) from None


@dataclass(frozen=True)
class SegmenterSource:
    """Segments each scan's frames with ``weights`` (once per build), then serves them like a detections file."""

    weights: str
    cache_dir: str
    coco_to_category: tuple[tuple[int, int], ...]  # (COCO id, dataset category id)
    stride: int
    min_score: float
    segmenter: SegmenterConfig
    device: str = "cpu"
    batch_size: int = 1

    def open_scan(self, scan: ColorScan) -> ScanDetections:
        path = Path(self.cache_dir) / f"{scan.scene_id}.json"
        frames = self._read_cache(path, scan)
        if frames is None:
            frames = self._segment(scan)
            path.parent.mkdir(parents=True, exist_ok=True)
            write_json_atomic(path, {"format": CACHE_FORMAT, "scene_id": scan.scene_id, "frames": frames}, indent=None)
        mapping = dict(self.coco_to_category)
        height, width = scan.color_size[1], scan.color_size[0]
        by_frame = {
            int(frame): [
                Detection(mapping[d["category_id"]], float(d["score"]), _rle(d["counts"], height, width)) for d in found
            ]
            for frame, found in frames.items()
        }
        return ScanDetections(by_frame)

    def _segment(self, scan: ColorScan) -> dict[str, list[dict[str, Any]]]:
        from usl.inference.segment import encode_masks

        segmenter = _segmenter(self.weights, self.segmenter, self.device)
        kept = dict(self.coco_to_category)
        indices = scan.frame_indices[:: self.stride]
        frames: dict[str, list[dict[str, Any]]] = {}
        for start in range(0, len(indices), self.batch_size):
            batch = indices[start : start + self.batch_size]
            for index, found in zip(batch, segmenter([scan.color(i) for i in batch]), strict=True):
                keep = [
                    k
                    for k, (category, score) in enumerate(zip(found.category_ids, found.scores, strict=True))
                    if int(category) in kept and score >= self.min_score
                ]
                rles = encode_masks(found.masks[keep])
                frames[str(index)] = [
                    {"category_id": int(found.category_ids[k]), "score": float(found.scores[k]), "counts": r["counts"]}
                    for k, r in zip(keep, rles, strict=True)
                ]
        return frames

    def _read_cache(self, path: Path, scan: ScanInfo) -> dict[str, list[dict[str, Any]]] | None:
        """A finished scan's detections; None if not segmented yet (a torn or foreign file is an error)."""
        try:
            data = json.loads(path.read_text())
        except FileNotFoundError:
            return None
        except (OSError, ValueError) as exc:
            raise UslError(f"{path}: unreadable cached detections ({exc}); delete the file to segment again") from None
        if not isinstance(data, dict) or data.get("format") != CACHE_FORMAT or data.get("scene_id") != scan.scene_id:
            raise UslError(f"{path}: not this build's cached detections of {scan.scene_id}; delete it to segment again")
        return data["frames"]


def _rle(counts: str, height: int, width: int) -> dict[str, Any]:
    return {"size": [height, width], "counts": counts.encode("ascii")}
