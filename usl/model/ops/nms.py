"""Non-maximum suppression with torchvision's contract, in pure torch.

Overlaps are computed in blocks of rows on the tensors' device; only the inherently
sequential greedy pass runs on the CPU (numpy), one cheap step per candidate box.
Boxes are ordered by group, then by decreasing score, so each row only needs the
later boxes *of its own group*: batched NMS costs the sum of the per-group triangles,
not the square of all boxes, and rows already suppressed are skipped entirely.
"""
from __future__ import annotations

from typing import Optional

import numpy as np
import torch

from .boxes import box_iou

Tensor = torch.Tensor

# Rows of the overlap matrix computed per step of the greedy pass.
_ROW_BLOCK = 256


def nms(boxes: Tensor, scores: Tensor, iou_threshold: float) -> Tensor:
    """Indices of the boxes kept by greedy NMS, in decreasing score order.

    A box is dropped when its IoU with a higher-scored kept box is ``> iou_threshold``.
    Equal scores are ranked by index (stable sort), so results are deterministic.
    """
    _check(boxes, scores)
    order = torch.sort(scores, descending=True, stable=True).indices
    return order[_to_device(_greedy_keep(boxes[order], iou_threshold, None), order)]


def batched_nms(boxes: Tensor, scores: Tensor, idxs: Tensor, iou_threshold: float) -> Tensor:
    """NMS applied independently within each group ``idxs`` (e.g. class or FPN level).

    Returns kept indices over all groups, in decreasing score order (ties by index).
    """
    _check(boxes, scores)
    if idxs.shape != scores.shape:
        raise ValueError(f"batched_nms expects idxs (N,), got {tuple(idxs.shape)} for {scores.shape[0]} boxes")
    by_score = torch.sort(scores, descending=True, stable=True).indices
    order = by_score[torch.sort(idxs[by_score], stable=True).indices]  # group-major, score-descending
    kept = order[_to_device(_greedy_keep(boxes[order], iou_threshold, idxs[order]), order)]
    kept = torch.sort(kept).values  # index order, so that equal scores rank as in nms()
    return kept[torch.sort(scores[kept], descending=True, stable=True).indices]


def _greedy_keep(sorted_boxes: Tensor, iou_threshold: float, groups: Optional[Tensor]) -> np.ndarray:
    """Positions kept by the greedy pass over boxes sorted by (group, decreasing score)."""
    count = sorted_boxes.shape[0]
    if groups is None:
        group_end = np.full(count, count, dtype=np.int64)
    else:
        group_ids = groups.cpu().numpy()
        boundaries = np.flatnonzero(np.diff(group_ids)) + 1
        ends = np.append(boundaries, count)
        group_end = np.repeat(ends, np.diff(np.concatenate([[0], ends])))
    suppressed = np.zeros(count, dtype=bool)
    keep = []
    for begin in range(0, count, _ROW_BLOCK):
        rows = np.flatnonzero(~suppressed[begin : begin + _ROW_BLOCK]) + begin
        if rows.size == 0:
            continue
        end = int(group_end[rows].max())
        row_index = _to_device(rows, sorted_boxes)
        overlaps = box_iou(sorted_boxes[row_index], sorted_boxes[begin:end]) > iou_threshold
        if groups is not None:
            overlaps &= groups[row_index][:, None] == groups[None, begin:end]
        overlaps = overlaps.cpu().numpy()
        for row, i in enumerate(rows):
            if suppressed[i]:
                continue
            keep.append(i)
            suppressed[i + 1 : end] |= overlaps[row, i + 1 - begin :]
    return np.asarray(keep, dtype=np.int64)


def _to_device(indices: np.ndarray, like: Tensor) -> Tensor:
    return torch.from_numpy(indices).to(like.device)


def _check(boxes: Tensor, scores: Tensor) -> None:
    if boxes.dim() != 2 or boxes.shape[1] != 4 or scores.shape != boxes.shape[:1]:
        raise ValueError(
            f"nms expects boxes (N, 4) and scores (N,), got {tuple(boxes.shape)} and {tuple(scores.shape)}"
        )
