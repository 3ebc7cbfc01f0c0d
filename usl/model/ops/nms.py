"""Non-maximum suppression with torchvision's contract, in three implementations that agree exactly.

* CPU, float32/float64: the greedy loop itself, compiled by numba over boxes sorted by score (and
  group), contiguous in memory. It is torchvision's algorithm without its indirect indexing, and
  beats its CPU kernel (``scripts/bench/nms.py``); numba caches the compiled loop on disk.
* CUDA: ``torchvision.ops.nms`` where torchvision loads and agrees with the pure-torch path on a
  probe set (checked once per device type); otherwise the pure-torch path below.
* Pure torch, on the boxes' device: greedy NMS as a graph problem, so nothing walks the boxes
  one by one. (1) A spatial hash join finds the pairs that *can* exceed the threshold (IoU > t
  needs side ratios above t and centres closer than ``(1 - t) max(w)``, ``(1 - t) max(h)``); their
  exact IoUs give the suppression edges, earlier score rank -> later rank. (2) ``keep[j] = not
  any(keep[i] for edges i -> j)`` iterated from ``keep = all`` fixes ranks in order and has a
  unique fixed point, so the first repeat is exactly the greedy result; each iteration is one
  gather and one scatter, and clusters settle in a handful of iterations. Its stop test is the
  only device-to-host synchronisation.

Every path compares IoUs with the threshold as a real number (as torchvision does) and ranks
equal scores by index.
"""

from __future__ import annotations

import math
from typing import Optional

import numpy as np
import torch

Tensor = torch.Tensor

_CHUNK_ELEMENTS = 1 << 22  # candidate pairs whose IoU is computed at once
# The candidate search is loosened by 1% so that rounding in the IoUs never makes it miss a true pair.
_ROUNDING_MARGIN = 0.99


def nms(boxes: Tensor, scores: Tensor, iou_threshold: float) -> Tensor:
    """Indices of the boxes kept by greedy NMS, in decreasing score order.

    A box is dropped when its IoU with a higher-scored kept box is ``> iou_threshold``.
    Equal scores are ranked by index (stable sort), so results are deterministic.
    """
    _check(boxes, scores)
    if _use_compiled(boxes):
        return _compiled_batched_nms(boxes, scores, None, iou_threshold)
    if _use_torchvision(boxes):
        return _torchvision_nms(boxes, scores, iou_threshold)
    return _pure_torch_nms(boxes, scores, iou_threshold)


def batched_nms(boxes: Tensor, scores: Tensor, idxs: Tensor, iou_threshold: float) -> Tensor:
    """NMS applied independently within each group ``idxs`` (e.g. class or FPN level).

    Returns kept indices over all groups, in decreasing score order (ties by index).
    """
    _check(boxes, scores)
    if idxs.shape != scores.shape:
        raise ValueError(f"batched_nms expects idxs (N,), got {tuple(idxs.shape)} for {scores.shape[0]} boxes")
    if _use_compiled(boxes):
        return _compiled_batched_nms(boxes, scores, idxs, iou_threshold)
    if _use_torchvision(boxes):
        return _torchvision_batched_nms(boxes, scores, idxs, iou_threshold)
    return _pure_torch_batched_nms(boxes, scores, idxs, iou_threshold)


# ----------------------------------------------------------------------------- pure torch
def _pure_torch_nms(boxes: Tensor, scores: Tensor, iou_threshold: float) -> Tensor:
    order = _score_order(scores)
    return order[_greedy(boxes[order], None, iou_threshold)]


def _pure_torch_batched_nms(boxes: Tensor, scores: Tensor, idxs: Tensor, iou_threshold: float) -> Tensor:
    order = _score_order(scores)
    return order[_greedy(boxes[order], idxs[order], iou_threshold)]


def _score_order(scores: Tensor) -> Tensor:
    return torch.sort(scores, descending=True, stable=True).indices


def _greedy(boxes: Tensor, groups: Optional[Tensor], threshold: float) -> Tensor:
    """Positions (ascending) kept by greedy NMS over boxes already in score order."""
    count = boxes.shape[0]
    keep = torch.ones(count, dtype=torch.bool, device=boxes.device)
    if count < 2:
        return torch.nonzero(keep).squeeze(1)
    source, target = _suppression_edges(boxes, groups, threshold)
    hits = torch.zeros(count, dtype=torch.int32, device=boxes.device)
    while True:
        settled = hits.zero_().index_add_(0, target, keep[source].int()) == 0
        if torch.equal(settled, keep):
            return torch.nonzero(keep).squeeze(1)
        keep = settled


def _suppression_edges(boxes: Tensor, groups: Optional[Tensor], threshold: float) -> tuple[Tensor, Tensor]:
    """All pairs (earlier rank, later rank) of one group whose IoU exceeds ``threshold``."""
    if threshold < 0:  # even disjoint boxes suppress each other: every pair is a candidate
        first, second = torch.triu_indices(len(boxes), len(boxes), 1, device=boxes.device)
    else:
        first, second = _candidate_pairs(boxes, groups, threshold * _ROUNDING_MARGIN)
    sources, targets = [], []
    for start in range(0, first.numel(), _CHUNK_ELEMENTS):
        i, j = first[start : start + _CHUNK_ELEMENTS], second[start : start + _CHUNK_ELEMENTS]
        above = _above(_pair_iou(boxes[i], boxes[j]), threshold)
        if groups is not None:
            above &= groups[i] == groups[j]
        sources.append(torch.minimum(i, j)[above])
        targets.append(torch.maximum(i, j)[above])
    if not sources:
        empty = torch.zeros(0, dtype=torch.long, device=boxes.device)
        return empty, empty
    return torch.cat(sources), torch.cat(targets)


def _candidate_pairs(boxes: Tensor, groups: Optional[Tensor], threshold: float) -> tuple[Tensor, Tensor]:
    """Pairs (i, j) that can have IoU > threshold, each unordered pair once: a spatial hash join.

    IoU > t needs both side ratios above t, so the longer sides m = max(w, h) differ by less than
    1/t and their octaves k = floor(log2 m) by at most ``spread``; it also needs the centres closer
    than ``(1 - t) max(w)`` in x (and likewise in y), below the cell size ``(1 - t) 2^(k+1)`` of the
    larger box's octave. So each box j is hashed into its octave's grid, each box i into the 3 x 3
    cells around it in the grids of octaves ``k_i .. k_i + spread``, and equal keys pair up.
    Boxes with a non-positive or non-finite side never exceed a threshold >= 0 and are left out.
    """
    device = boxes.device
    x0, y0, x1, y1 = boxes.double().unbind(1)
    w, h = x1 - x0, y1 - y0
    usable = torch.nonzero(torch.isfinite(boxes).all(1) & (w > 0) & (h > 0)).squeeze(1)
    count = usable.numel()
    spread = math.ceil(1.0 + math.log2(1.0 / threshold)) - 1 if threshold > 0 else None
    if threshold >= 1.0 or count < 2:  # IoU never exceeds 1
        return usable[:0], usable[:0]
    if spread is None or spread > 8:  # tiny thresholds pair (almost) everything: no hashing
        first, second = torch.triu_indices(count, count, 1, device=device)
        return usable[first], usable[second]
    w, h = w[usable], h[usable]
    centre_x, centre_y = (x0[usable] + x1[usable]) / 2, (y0[usable] + y1[usable]) / 2
    octave = torch.floor(torch.log2(torch.maximum(w, h))).long()
    group = None if groups is None else torch.unique(groups[usable], return_inverse=True)[1]

    # Build side: each box in its own octave's grid. Query side: each box in the grids of octaves
    # k .. k + spread, at the 3 x 3 cells around its centre.
    build = _grid_cells(centre_x, centre_y, octave, threshold)
    query_box = torch.arange(count, device=device).repeat_interleave(spread + 1)
    query_octave = octave[query_box] + torch.arange(spread + 1, device=device).repeat(count)
    qx, qy = _grid_cells(centre_x[query_box], centre_y[query_box], query_octave, threshold)
    around = torch.tensor([-1, 0, 1], device=device)
    qx = (qx[:, None, None] + around[None, :, None]).expand(-1, 3, 3).reshape(-1)
    qy = (qy[:, None, None] + around[None, None, :]).expand(-1, 3, 3).reshape(-1)
    query_box, query_octave = query_box.repeat_interleave(9), query_octave.repeat_interleave(9)
    keys = _cell_keys((octave, *build, group), (query_octave, qx, qy, None if group is None else group[query_box]))
    if keys is None:  # the key range would overflow int64: compare all pairs instead
        first, second = torch.triu_indices(count, count, 1, device=device)
        return usable[first], usable[second]
    build_key, query_key = keys
    order = torch.argsort(build_key)
    sorted_keys = build_key[order]
    low = torch.searchsorted(sorted_keys, query_key, side="left")
    matches = torch.searchsorted(sorted_keys, query_key, side="right") - low
    total = int(matches.sum())
    # Expand each query to its run of matching build entries.
    run_start = torch.repeat_interleave(low - (torch.cumsum(matches, 0) - matches), matches, output_size=total)
    j = order[run_start + torch.arange(total, device=device)]
    i = torch.repeat_interleave(query_box, matches, output_size=total)
    # Same octave: each pair is found from both boxes, keep i < j; across octaves i is the smaller.
    keep = (octave[i] < octave[j]) | ((octave[i] == octave[j]) & (i < j))
    return usable[i[keep]], usable[j[keep]]


def _grid_cells(x: Tensor, y: Tensor, octave: Tensor, threshold: float) -> tuple[Tensor, Tensor]:
    cell = (1.0 - threshold) * torch.exp2(octave.double() + 1)
    return torch.floor(x / cell).long(), torch.floor(y / cell).long()


def _cell_keys(build: tuple, query: tuple) -> Optional[tuple[Tensor, Tensor]]:
    """One int64 key per (group, octave, cell x, cell y) for both sides, or None on overflow."""
    lows, spans = [], []
    for b, q in zip(build[:3], query[:3]):
        low = torch.minimum(b.min(), q.min())
        lows.append(low)
        spans.append(int(torch.maximum(b.max(), q.max()) - low) + 1)
    groups = 1 if build[3] is None else int(build[3].max()) + 1
    if float(math.prod(spans)) * groups >= 2.0**62:
        return None

    def key(parts: tuple) -> Tensor:
        value = parts[0] - lows[0]
        for part, low, span in zip(parts[1:3], lows[1:], spans[1:]):
            value = value * span + (part - low)
        return value if parts[3] is None else value + parts[3] * math.prod(spans)

    return key(build), key(query)


def _pair_iou(first: Tensor, second: Tensor) -> Tensor:
    """IoU of row k of ``first`` with row k of ``second``, with the arithmetic of ``box_iou``."""
    ax0, ay0, ax1, ay1 = first.unbind(1)
    bx0, by0, bx1, by1 = second.unbind(1)
    inter = (torch.minimum(ax1, bx1) - torch.maximum(ax0, bx0)).clamp_(min=0)
    inter *= (torch.minimum(ay1, by1) - torch.maximum(ay0, by0)).clamp_(min=0)
    union = ((ax1 - ax0) * (ay1 - ay0) + (bx1 - bx0) * (by1 - by0)).sub_(inter)
    return inter.div_(union)


def _above(iou: Tensor, threshold: float) -> Tensor:
    """``iou > threshold`` with the threshold as a real number (as torchvision compares it).

    A plain comparison would round ``threshold`` to the IoU's precision first; where that rounds
    up, ``>=`` against the rounded value is the exact test.
    """
    rounded = torch.tensor(threshold, dtype=iou.dtype).item()
    return iou >= rounded if rounded > threshold else iou > rounded


# ----------------------------------------------------------------------------- compiled (CPU)
def _use_compiled(boxes: Tensor) -> bool:
    return _greedy_kernel is not None and boxes.device.type == "cpu" and boxes.dtype in (torch.float32, torch.float64)


def _compiled_batched_nms(boxes: Tensor, scores: Tensor, idxs: Optional[Tensor], iou_threshold: float) -> Tensor:
    order = _score_order(scores)
    if idxs is None:
        group_end = np.full(len(order), len(order), dtype=np.int64)
    else:
        order = order[torch.sort(idxs[order], stable=True).indices]  # group-major, score-descending
        group_ids = idxs[order].numpy()
        ends = np.append(np.flatnonzero(np.diff(group_ids)) + 1, len(order)).astype(np.int64)
        group_end = np.repeat(ends, np.diff(np.concatenate([[0], ends])))
    x0, y0, x1, y1 = (np.ascontiguousarray(c) for c in boxes[order].numpy().T)
    area = (x1 - x0) * (y1 - y0)
    inert = np.isnan(area) | np.isnan(x0) | np.isnan(y0) | np.isnan(x1) | np.isnan(y1)
    keep = np.empty(len(order), dtype=np.int64)
    suppressed = np.zeros(len(order), dtype=bool)
    count = _greedy_kernel(x0, y0, x1, y1, area, inert, group_end, float(iou_threshold), suppressed, keep)
    kept = order[torch.from_numpy(keep[:count])]
    if idxs is None:
        return kept
    kept = torch.sort(kept).values  # index order, so that equal scores rank as in nms()
    return kept[torch.sort(scores[kept], descending=True, stable=True).indices]


def _greedy_loop(x0, y0, x1, y1, area, inert, group_end, threshold, suppressed, keep):  # pragma: no cover
    """Greedy NMS over boxes in processing order (runs compiled); box i may suppress j in
    ``(i, group_end[i])``. Writes kept positions to ``keep`` and returns how many.

    box_iou's arithmetic in the boxes' precision. ``inert`` boxes (a NaN coordinate: NaN IoUs)
    neither suppress nor are suppressed. Outputs are preallocated so the compiled code never
    allocates (which would load numba's runtime at import-time cost).
    """
    kept = 0
    for i in range(x0.shape[0]):
        if suppressed[i]:
            continue
        keep[kept] = i
        kept += 1
        if inert[i]:
            continue
        for j in range(i + 1, group_end[i]):
            if suppressed[j] or inert[j]:
                continue
            w = (x1[i] if x1[i] < x1[j] else x1[j]) - (x0[i] if x0[i] > x0[j] else x0[j])
            h = (y1[i] if y1[i] < y1[j] else y1[j]) - (y0[i] if y0[i] > y0[j] else y0[j])
            if w < 0:  # clamp to +0 in the boxes' precision (a 0.0 literal would promote to float64)
                w = w - w
            if h < 0:
                h = h - h
            inter = w * h
            if inter / (area[i] + area[j] - inter) > threshold:  # float64 threshold: a real comparison
                suppressed[j] = True
    return kept


try:  # numba is a dependency; without it the pure-torch path serves the CPU too
    import numba
except ImportError:
    numba = None
# numpy's error model: x / 0 gives inf/nan as in torch; cache: compiled once per machine, on disk.
_greedy_kernel = numba.njit(cache=True, nogil=True, error_model="numpy")(_greedy_loop) if numba else None


# ----------------------------------------------------------------------------- torchvision
def _torchvision_nms(boxes: Tensor, scores: Tensor, iou_threshold: float) -> Tensor:
    """torchvision's kernel on boxes we put in score order ourselves, with distinct surrogate
    scores, so equal scores rank by index exactly as in the pure-torch path."""
    order = _score_order(scores)
    ranks = torch.arange(len(order), 0, -1, device=boxes.device, dtype=boxes.dtype)
    return order[_TORCHVISION.nms(boxes[order], ranks, iou_threshold)]


def _torchvision_batched_nms(boxes: Tensor, scores: Tensor, idxs: Tensor, iou_threshold: float) -> Tensor:
    """One torchvision NMS per group (its own batched_nms offsets coordinates, which rounds)."""
    order = _score_order(scores)
    boxes, groups = boxes[order], idxs[order]
    kept = [torch.zeros(0, dtype=torch.long, device=boxes.device)]
    for group in torch.unique(groups):
        members = torch.nonzero(groups == group).squeeze(1)
        ranks = torch.arange(len(members), 0, -1, device=boxes.device, dtype=boxes.dtype)
        kept.append(members[_TORCHVISION.nms(boxes[members], ranks, iou_threshold)])
    return order[torch.sort(torch.cat(kept)).values]


def _load_torchvision():
    try:
        import torchvision.ops as ops

        ops.nms(torch.zeros(1, 4), torch.zeros(1), 0.5)
        return ops
    except Exception:  # not installed, or its compiled kernels do not load beside this torch
        return None


_TORCHVISION = _load_torchvision()
_PROVEN: dict[str, bool] = {}  # device type -> torchvision agrees with the pure-torch path


def _use_torchvision(boxes: Tensor) -> bool:
    if _TORCHVISION is None or boxes.dtype not in (torch.float32, torch.float64):
        return False
    device = boxes.device.type
    if device not in _PROVEN:
        _PROVEN[device] = _agrees_with_torchvision(boxes.device)
    return _PROVEN[device]


def _agrees_with_torchvision(device: torch.device) -> bool:
    """Both paths on a probe set with clusters, ties, groups and both dtypes: any difference and
    torchvision is not used on this device."""
    generator = np.random.default_rng(0)
    centres = generator.uniform(0, 500, (40, 2)).repeat(30, axis=0) + generator.normal(0, 8, (1200, 2))
    sizes = generator.uniform(10, 120, (40, 2)).repeat(30, axis=0) * generator.uniform(0.8, 1.25, (1200, 2))
    boxes = torch.from_numpy(np.concatenate([centres - sizes / 2, centres + sizes / 2], axis=1)).to(device)
    scores = torch.from_numpy(generator.integers(0, 50, 1200).astype(np.float64)).to(device)  # many ties
    groups = torch.from_numpy(generator.integers(0, 4, 1200)).to(device)
    try:
        for dtype in (torch.float32, torch.float64):
            b, s = boxes.to(dtype), scores.to(dtype)
            for threshold in (0.3, 0.5, 0.7):
                if not torch.equal(_torchvision_nms(b, s, threshold), _pure_torch_nms(b, s, threshold)):
                    return False
                if not torch.equal(
                    _torchvision_batched_nms(b, s, groups, threshold), _pure_torch_batched_nms(b, s, groups, threshold)
                ):
                    return False
    except Exception:  # e.g. torchvision built without this device's kernels
        return False
    return True


def _check(boxes: Tensor, scores: Tensor) -> None:
    if boxes.dim() != 2 or boxes.shape[1] != 4 or scores.shape != boxes.shape[:1]:
        raise ValueError(
            f"nms expects boxes (N, 4) and scores (N,), got {tuple(boxes.shape)} and {tuple(scores.shape)}"
        )
