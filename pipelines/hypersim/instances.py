"""Per-frame instance ground truth from a label image, all instances in one pass.

``instance_entries`` returns exactly what ``usl.records.make_instance`` returns for each
``labels == id`` mask (RLE, box, area, nearest depth; tested equal), but from the runs of the
column-major label image: O(pixels + runs) for the whole frame instead of several full-image passes
per instance. At Hypersim's ~50 instances per 1024x768 image that is ~30 ms per frame instead of
~50 x 11 ms on the 2-core CI machine.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from pycocotools import mask as mask_utils

NUM_CATEGORIES = 40  # NYU40 ids 1..40; 0 in vote tables means "unlabelled"


# int16 label value (viewed as uint16) -> NYU40 id, 0 for anything outside 1..40.
_NYU40_OF_INT16 = np.zeros(1 << 16, np.int32)
_NYU40_OF_INT16[1 : NUM_CATEGORIES + 1] = np.arange(1, NUM_CATEGORIES + 1)


def category_votes(instance: np.ndarray, semantic: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Instance ids >= 1 present in the frame, and per id its pixel count for each NYU40 label
    (column 0: pixels without a valid label), shape (n, 41)."""
    ids = np.maximum(instance, 0).astype(np.int64)
    top = int(ids.max(initial=0))
    if top < 1:
        return np.zeros(0, np.int64), np.zeros((0, NUM_CATEGORIES + 1), np.int64)
    if semantic.dtype.itemsize <= 2 and np.issubdtype(semantic.dtype, np.integer):
        labels = _NYU40_OF_INT16[semantic.astype(np.int16).view(np.uint16)]
    else:
        labels = np.where((semantic >= 1) & (semantic <= NUM_CATEGORIES), semantic, 0)
    ids *= NUM_CATEGORIES + 1
    ids += labels
    table = np.bincount(ids.ravel(), minlength=(top + 1) * (NUM_CATEGORIES + 1))
    table = table.reshape(top + 1, NUM_CATEGORIES + 1)
    present = np.flatnonzero(table[1:].sum(axis=1)) + 1
    return present, table[present]


def _rle_counts(starts: np.ndarray, ends: np.ndarray, total: int) -> list[int]:
    """COCO's uncompressed counts (zeros first, alternating) of one instance's runs."""
    counts = np.empty(2 * len(starts) + 1, dtype=np.int64)
    counts[0] = starts[0]
    counts[1::2] = ends - starts
    counts[2:-1:2] = starts[1:] - ends[:-1]
    counts[-1] = total - ends[-1]
    return counts[:-1].tolist() if counts[-1] == 0 else counts.tolist()


def _runs(flat: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Maximal runs of equal values of a 1-D array: (starts, ends, values)."""
    change = np.flatnonzero(flat[1:] != flat[:-1]) + 1
    starts = np.concatenate(([0], change))
    return starts, np.concatenate((change, [flat.size])), flat[starts]


def _grouped(values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Runs with an instance id (>= 1) sorted by id: (run order, ids, first position of each id)."""
    keep = np.flatnonzero(values >= 1)
    order = keep[np.argsort(values[keep], kind="stable")]
    ids, first = np.unique(values[order], return_index=True)
    return order, ids, first


def _nearest_depth(labels: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Per instance id (ascending), the smallest depth over its pixels; NaN if none is known.

    Uses row-major runs so the depth image is never transposed; ``fmin`` skips NaN."""
    starts, _, values = _runs(labels.ravel())
    order, _, first = _grouped(values)
    return np.fmin.reduceat(np.fmin.reduceat(depth.ravel(), starts)[order], first)


def instance_entries(labels: np.ndarray, depth: np.ndarray | None) -> list[dict[str, Any]]:
    """One entry per instance id >= 1 in ``labels`` (ascending), without ``category_id``.

    ``depth``: planar depth with NaN where unknown (other values positive and finite), or None.
    """
    height, width = labels.shape
    flat = np.ascontiguousarray(labels.T).ravel()  # column-major, the order of COCO RLE
    starts, ends, values = _runs(flat)
    order, ids, first = _grouped(values)
    if order.size == 0:
        return []
    starts, ends = starts[order], ends[order]
    area = np.add.reduceat(ends - starts, first)
    col0, col1 = starts // height, (ends - 1) // height
    single_column = col0 == col1
    row0 = np.where(single_column, starts % height, 0)
    row1 = np.where(single_column, (ends - 1) % height, height - 1)
    x0, x1 = np.minimum.reduceat(col0, first), np.maximum.reduceat(col1, first) + 1
    y0, y1 = np.minimum.reduceat(row0, first), np.maximum.reduceat(row1, first) + 1
    nearest = _nearest_depth(labels, depth) if depth is not None else np.full(len(ids), np.nan)
    bounds = np.append(first, len(order))
    rles = mask_utils.frPyObjects(
        [
            {"size": [height, width], "counts": _rle_counts(starts[a:b], ends[a:b], flat.size)}
            for a, b in zip(bounds[:-1], bounds[1:], strict=True)
        ],
        height,
        width,
    )
    return [
        {
            "instance_id": int(ids[k]),
            "mask": {"size": [height, width], "counts": rles[k]["counts"].decode("ascii")},
            "box_xyxy": [float(x0[k]), float(y0[k]), float(x1[k]), float(y1[k])],
            "area": int(area[k]),
            "depth_min": float(nearest[k]),
        }
        for k in range(len(ids))
    ]
