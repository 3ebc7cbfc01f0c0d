"""2D instance masks per frame: the ``MaskSource`` protocol every mask provider implements.

Three providers plug in here: a COCO results file written by a segmenter run elsewhere
(``detections_file``), ScanNet's own ``instance-filt`` images (``scannet_labels``), and later the
project's own detector. Each returns, per frame, ``Detection`` objects whose masks are COCO RLE in
the colour image's pixel frame: any resolution covering the whole colour image, one size per scan
(tracking compares masks at that resolution; records resample them to the output grid).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

RLE = dict[str, Any]  # pycocotools form: {"size": [h, w], "counts": bytes}


@dataclass(frozen=True)
class Detection:
    """One instance mask in one frame.

    ``category_id`` is the *dataset* category (data_specs/scannet.yaml ``id``), already mapped
    from the source's own ids. ``source_id`` is an identity the source already knows (ScanNet's
    instance ids), used to measure the tracker or to bypass it; None for detectors.
    """

    category_id: int
    score: float
    rle: RLE
    source_id: int | None = None


@dataclass(frozen=True)
class FrameView:
    """What a mask source may look at: the frame's index and, on demand, its RGB image."""

    index: int
    color: Callable[[], np.ndarray]


class ScanMasks(Protocol):
    """The masks of one opened scan."""

    def detect(self, frame: FrameView) -> list[Detection]: ...


class ScanInfo(Protocol):
    """The scan facts a mask source may check against (satisfied by every scan reader)."""

    scene_id: str
    path: Any
    color_size: tuple[int, int]
    frame_indices: list[int]


class MaskSource(Protocol):
    """A picklable description of a mask provider, opened once per scan inside a build worker."""

    def open_scan(self, scan: ScanInfo) -> ScanMasks: ...


def rle_counts(counts: str | bytes) -> np.ndarray:
    """Run lengths of a compressed COCO RLE string, checked so pycocotools never reads past a buffer.

    The string packs each count in 5-bit groups (chars 48..111, bit 0x20 = "more follows", bit 0x10
    of the last group = sign) and stores counts from the third on as differences to the count two
    places before. pycocotools decodes such strings without bounds checks, so malformed input must
    be rejected here first. Raises ValueError.
    """
    data = np.frombuffer(counts.encode("ascii") if isinstance(counts, str) else bytes(counts), np.uint8)
    if data.size == 0:
        raise ValueError("empty counts string")
    values = data.astype(np.int64) - 48
    if values.min() < 0 or values.max() > 63:
        raise ValueError("counts string has characters outside the RLE alphabet")
    last = (values & 0x20) == 0
    if not last[-1]:
        raise ValueError("counts string ends inside a number")
    ends = np.flatnonzero(last)
    starts = np.concatenate([[0], ends[:-1] + 1])
    position = np.arange(values.size) - np.repeat(starts, ends - starts + 1)
    if position.max() > 5:  # pycocotools shifts in 32-bit ints: six 5-bit groups at most
        raise ValueError("counts string has a number longer than 30 bits")
    numbers = np.add.reduceat((values & 0x1F) << (5 * position), starts)
    negative = (values[ends] & 0x10) != 0
    numbers = numbers - (negative.astype(np.int64) << (5 * (position[ends] + 1)))
    runs = numbers.copy()
    runs[3::2] = np.cumsum(numbers[1::2])[1:]  # counts[i] += counts[i-2] for i > 2
    runs[2::2] = np.cumsum(numbers[2::2])
    if (runs < 0).any():
        raise ValueError("negative run length")
    return runs


def checked_rle(segmentation: Any, height: int | None = None, width: int | None = None) -> RLE:
    """A segmentation from a results file as a pycocotools RLE, or ValueError saying what is wrong.

    Accepts compressed (string counts) and uncompressed (list counts) RLE; the runs must cover the
    ``size`` exactly, and ``size`` must equal (height, width) when given. Polygons are refused:
    detectron2 writes masks as RLE.
    """
    if not isinstance(segmentation, dict) or "size" not in segmentation or "counts" not in segmentation:
        raise ValueError("segmentation is not an RLE dict with 'size' and 'counts' (polygons are not supported)")
    size = segmentation["size"]
    if not (isinstance(size, (list, tuple)) and len(size) == 2 and all(isinstance(s, int) and s > 0 for s in size)):
        raise ValueError(f"RLE size {size!r} is not [height, width]")
    h, w = int(size[0]), int(size[1])
    if height is not None and (h, w) != (height, width):
        raise ValueError(f"RLE size [{h}, {w}] differs from the image's [{height}, {width}]")
    counts = segmentation["counts"]
    if isinstance(counts, list):
        runs = np.asarray(counts, dtype=np.int64)
        if runs.ndim != 1 or (runs < 0).any():
            raise ValueError("uncompressed RLE counts must be non-negative integers")
    elif isinstance(counts, (str, bytes)):
        runs = rle_counts(counts)
    else:
        raise ValueError(f"RLE counts of type {type(counts).__name__}")
    if int(runs.sum()) != h * w:
        raise ValueError(f"RLE runs cover {int(runs.sum())} pixels, not {h}x{w} = {h * w}")
    if isinstance(counts, list):
        from pycocotools import mask as mask_utils

        return mask_utils.frPyObjects({"size": [h, w], "counts": [int(c) for c in runs]}, h, w)
    return {"size": [h, w], "counts": counts.encode("ascii") if isinstance(counts, str) else bytes(counts)}
