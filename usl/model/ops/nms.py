"""Non-maximum suppression with torchvision's contract, in three implementations that agree exactly.

* CPU, float32/float64: the greedy loop itself, compiled by numba over boxes sorted by score (and
  group), contiguous in memory. It is torchvision's algorithm without its indirect indexing, and
  beats its CPU kernel (``scripts/bench/nms.py``); numba caches the compiled loop on disk.
* CUDA: ``torchvision.ops.nms`` where torchvision loads and agrees with the pure-torch path on a
  probe set (checked once per device type); otherwise the pure-torch path below.
* Pure torch, on the boxes' device (also on the CPU inside ``usl.utils.compiled.torch_paths_only``,
  which is how ``scripts/bench/count_ops.py`` counts CUDA's NMS): greedy NMS as a graph problem,
  so nothing walks the boxes one by one. (1) A spatial hash join finds the pairs that *can* exceed
  the threshold (IoU > t needs side ratios above t and centres closer than ``(1 - t) max(w)``,
  ``(1 - t) max(h)``); their exact IoUs give the suppression edges, earlier score rank -> later
  rank, kept as a mask over the candidates rather than selected. (2) ``keep[j] = not any(keep[i]
  for edges i -> j)`` iterated from ``keep = all`` fixes ranks in order and has a unique fixed
  point, which is exactly the greedy result; each iteration is one gather and one scatter, and a
  detector's clusters settle within the first batch of rounds (8). Two host reads per call,
  whatever the number of boxes and groups: the number of candidate pairs, and one stop test per
  batch of rounds (a chain of suppressions longer than a batch takes more, each batch twice the
  last), whose count of kept boxes sizes the output. Beyond 4M candidate pairs (where the IoUs
  are computed in chunks) one more read selects the edges, which the rounds then iterate over.

Every path compares IoUs with the threshold as a real number (as torchvision does) and ranks
equal scores by index.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ...utils.compiled import compiled, serves

Tensor = torch.Tensor

_CHUNK_ELEMENTS = 1 << 22  # candidate pairs whose IoU is computed at once
_ROUNDS_PER_TEST = 8  # fixed-point rounds between stop tests: enough for the clusters of a detector's boxes
# Cell keys (octave * span + cell x) * span + cell y, plus the group label's low bits above: the
# cells clamped to +-2^19 (then a neighbour's fields stay in [0, span)), in int64 without overflow.
_CELL_LIMIT = float(1 << 19)
_CELL_SPAN = (1 << 20) + 3
_GROUP_MASK, _GROUP_SHIFT = (1 << 10) - 1, 52
_NO_BOX = -(1 << 62)  # the key of an unusable box: below every cell's
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


def kept_by_image(kept: Tensor, image: Tensor, num_images: int) -> list[Tensor]:
    """``kept`` (indices from one NMS call over several images' boxes, ``image[k]`` the image of box
    k) split by image, each in decreasing score order (ties by index) as if NMS had run on that
    image alone: one host read, the number of boxes kept per image."""
    images, by_image = torch.sort(image[kept], stable=True)
    counts = (images[None] == torch.arange(num_images, device=kept.device)[:, None]).sum(1).tolist()
    return list(kept[by_image].split(counts))


# ----------------------------------------------------------------------------- pure torch
def _pure_torch_nms(boxes: Tensor, scores: Tensor, iou_threshold: float) -> Tensor:
    order = _score_order(scores)
    return order[_greedy(boxes[order], None, iou_threshold)]


def _pure_torch_batched_nms(boxes: Tensor, scores: Tensor, idxs: Tensor, iou_threshold: float) -> Tensor:
    order = _score_order(scores)
    return order[_greedy(boxes[order], idxs[order], iou_threshold)]


def _score_order(scores: Tensor) -> Tensor:
    return torch.sort(scores, descending=True, stable=True).indices


def _greedy(boxes: Tensor, groups: Tensor | None, threshold: float) -> Tensor:
    """Positions (ascending) kept by greedy NMS over boxes already in score order."""
    count = boxes.shape[0]
    if count < 2:
        return torch.arange(count, device=boxes.device)
    source, target = _suppression_edges(boxes, groups, threshold)
    if source.numel() > _CHUNK_ELEMENTS:  # the rounds' work is the candidates': beyond a chunk, keep the edges
        edges = torch.nonzero(target < count).squeeze(1)
        source, target = source[edges], target[edges]
    return _fixed_point(source, target, count)


def _fixed_point(source: Tensor, target: Tensor, count: int) -> Tensor:
    """Positions kept at the fixed point of ``keep[j] = not any(keep[i] for edges i -> j)``, from
    ``keep = all``; an edge with ``target == count`` is none.

    The map is antitone and starts from the top, so consecutive iterates are nested (alternately
    each a subset of the other): equal counts mean equal iterates, the fixed point. Rounds run in
    batches between stop tests (rounds past the fixed point change nothing), and a test reads both
    counts at once, the second being the output's size.
    """
    keep = torch.ones(count + 1, dtype=torch.int32, device=source.device)  # the last slot: non-edges' targets
    previous = torch.empty_like(keep)
    hits = torch.zeros_like(keep)
    rounds = _ROUNDS_PER_TEST
    while True:
        for _ in range(rounds):
            keep, previous = torch.eq(torch.index_add(hits, 0, target, keep[source]), 0, out=previous), keep
        before, kept = torch.stack([previous, keep])[:, :count].sum(1).tolist()
        if before == kept:
            return torch.nonzero_static(keep[:count], size=kept).squeeze(1)
        rounds *= 2  # a long suppression chain: fewer tests for it


def _suppression_edges(boxes: Tensor, groups: Tensor | None, threshold: float) -> tuple[Tensor, Tensor]:
    """Candidate pairs (earlier rank, later rank) and whether each is an edge: the later rank where
    the pair is of two boxes of one group whose IoU exceeds ``threshold``, ``len(boxes)`` where not."""
    count = len(boxes)
    if threshold < 0:  # even disjoint boxes suppress each other: every pair is a candidate
        source, target = torch.triu_indices(count, count, 1, device=boxes.device)
    else:
        source, target = _candidate_pairs(boxes, groups, threshold * _ROUNDING_MARGIN)
    corners = boxes.view(count, 2, 2)
    area = (corners[:, 1] - corners[:, 0]).prod(1)
    above = []
    for start in range(0, max(source.numel(), 1), _CHUNK_ELEMENTS):
        i, j = source[start : start + _CHUNK_ELEMENTS], target[start : start + _CHUNK_ELEMENTS]
        above.append(_above(_pair_iou(corners, area, i, j), threshold))
    edge = above[0] if len(above) == 1 else torch.cat(above)
    edge &= source < target  # not a box with itself
    if groups is not None:
        edge &= groups[source] == groups[target]
    return source, target.masked_fill(~edge, count)


def _candidate_pairs(boxes: Tensor, groups: Tensor | None, threshold: float) -> tuple[Tensor, Tensor]:
    """Pairs of boxes (earlier rank, later or equal rank) among which are all that have
    IoU > threshold: a spatial hash join.

    IoU > t needs both side ratios above t, so the longer sides m = max(w, h) differ by less than
    1/t and their octaves k = floor(log2 m) by at most ``spread``; it also needs the centres closer
    than ``(1 - t) max(w)`` in x (and likewise in y), below the cell size ``(1 - t) 2^(k+1)`` of the
    larger box's octave. So each box j is hashed into its octave's grid, each box i into the 3 x 3
    cells around it in the grids of octaves ``k_i .. k_i + spread``, and equal keys pair up.
    Boxes with a non-positive or non-finite side never exceed a threshold >= 0 and are hashed to a
    key no query has. The only host read is the number of pairs.
    """
    device, count = boxes.device, len(boxes)
    spread = math.ceil(1.0 + math.log2(1.0 / threshold)) - 1 if threshold > 0 else None
    if threshold >= 1.0:  # IoU never exceeds 1
        empty = torch.zeros(0, dtype=torch.long, device=device)
        return empty, empty
    if spread is None or spread > 8:  # tiny thresholds pair (almost) everything: no hashing
        first, second = torch.triu_indices(count, count, 1, device=device)
        return first, second
    low, high = boxes.double().view(count, 2, 2).unbind(1)
    size = high - low
    side = size.amax(1)
    unusable = ~((size.amin(1) > 0) & (side < math.inf))  # NaN too
    # Octaves clamped from below (a coarser grid only adds candidates) keep cell sizes positive.
    octave = side.masked_fill(unusable, 1.0).log2_().floor_().clamp_(min=-1000)
    # Key of box i's cell in the grid of octave k_i + s, for s = 0 .. spread (s = 0: its own cell).
    octaves = octave[:, None] + torch.arange(spread + 1, device=device, dtype=octave.dtype)
    twice_cell = torch.exp2(octaves).mul_(4 * (1.0 - threshold))
    cells = torch.div((low + high)[:, None], twice_cell[..., None], rounding_mode="floor")
    # Clamping keeps neighbouring cells neighbours and each key field within its span (an unusable
    # box's NaN becomes a cell too). Integers below 2^53: the key is exact in float64.
    x, y = cells.nan_to_num_().clamp_(-_CELL_LIMIT, _CELL_LIMIT).unbind(2)
    key = torch.add(y, torch.add(x, octaves, alpha=_CELL_SPAN), alpha=_CELL_SPAN).long()
    if groups is not None:  # group labels modulo 2^10: equal groups share the field, few others do
        key += (groups[:, None].long() & _GROUP_MASK) << _GROUP_SHIFT
    build_key = key[:, 0].masked_fill(unusable, _NO_BOX)  # unusable boxes' queries find only usable ones
    # The 3 x 3 cells around: key fields are linear and y the lowest, so the cells (x + dx, y - 1 ..
    # y + 1) are the key range (key + dx span - 1 .. key + dx span + 1).
    query_key = (key[:, :, None] + torch.arange(-1, 2, device=device) * _CELL_SPAN).view(-1)
    query_box = torch.arange(count, device=device).repeat_interleave(3 * (spread + 1))

    order = torch.argsort(build_key)
    sorted_keys = build_key[order]
    first = torch.searchsorted(sorted_keys, query_key - 1, side="left")
    last = torch.searchsorted(sorted_keys, query_key + 1, side="right")
    matches = last - first
    total = int(matches.sum())
    # Expand each query to its run of matching build entries.
    run_end = torch.repeat_interleave(last - torch.cumsum(matches, 0), matches, output_size=total)
    j = order[run_end + torch.arange(total, device=device)]
    i = torch.repeat_interleave(query_box, matches, output_size=total)
    # Pairs of one octave are found twice (an edge twice changes nothing) and each box pairs with
    # itself (the edge test drops those); keys equal by collision (clamped cells, group labels)
    # add pairs the IoU test drops.
    return torch.minimum(i, j), torch.maximum(i, j)


def _pair_iou(corners: Tensor, area: Tensor, i: Tensor, j: Tensor) -> Tensor:
    """IoU of boxes i[k] and j[k] (``corners`` (N, 2, 2), ``area`` (N,)), with the arithmetic of ``box_iou``."""
    first, second = corners[i], corners[j]
    near, far = torch.maximum(first, second)[:, 0], torch.minimum(first, second)[:, 1]
    inter = (far - near).clamp_(min=0).prod(1)
    return inter / (area[i] + area[j] - inter)


def _above(iou: Tensor, threshold: float) -> Tensor:
    """``iou > threshold`` with the threshold as a real number (as torchvision compares it): against
    the largest value of the IoU's dtype not above it, rounded on the host; dtypes numpy lacks
    compare in float64, which holds them and the Python float exactly."""
    dtype = _NUMPY_FLOATS.get(iou.dtype)
    if dtype is None:
        return iou.double() > threshold
    rounded = dtype(threshold)
    return iou > float(np.nextafter(rounded, dtype(-np.inf)) if float(rounded) > threshold else rounded)


_NUMPY_FLOATS = {torch.float16: np.float16, torch.float32: np.float32, torch.float64: np.float64}


# ----------------------------------------------------------------------------- compiled (CPU)
def _use_compiled(boxes: Tensor) -> bool:
    return serves(boxes) and boxes.dtype in (torch.float32, torch.float64)


def _compiled_batched_nms(boxes: Tensor, scores: Tensor, idxs: Tensor | None, iou_threshold: float) -> Tensor:
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


_greedy_kernel = compiled(_greedy_loop)


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
