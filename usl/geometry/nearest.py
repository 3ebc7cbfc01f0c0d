"""Batched, chunked nearest-neighbour search in torch (Chamfer losses and metrics), with a KD-tree
and a compiled brute-force loop for CPU tensors.

The search (which neighbour is nearest) runs without autograd over chunks of the query
points, so memory stays at ``chunk x M`` distances per batch element instead of N x M;
it uses the fast matrix-product form of the distance (near-ties may pick either point).
The returned squared distances are then recomputed from the gathered neighbours, so
they are exactly differentiable w.r.t. both point sets (the gradient of a minimum is
the gradient of its minimiser), at O(N) extra memory.
"""

from __future__ import annotations

import numpy as np
import torch

from usl.geometry.kdtree_search import nearest_in_tree
from usl.utils.compiled import compiled, serves
from usl.utils.transfer import to_device

Tensor = torch.Tensor

# Distances computed per chunk across the whole batch (about 128 MiB in float32).
DEFAULT_MAX_ELEMENTS = 1 << 25


def lengths_to_mask(lengths: Tensor, max_len: int) -> Tensor:
    """(B,) counts -> (B, max_len) boolean mask of the first ``lengths[b]`` entries."""
    return torch.arange(max_len, device=lengths.device) < lengths.unsqueeze(-1)


def nearest_neighbors(
    x: Tensor,
    y: Tensor,
    y_valid: Tensor | None = None,
    max_elements: int = DEFAULT_MAX_ELEMENTS,
    backend: str = "torch",
) -> tuple[Tensor, Tensor]:
    """For every point of x, its nearest valid point of y (Euclidean, any dimension D).

    Args:
        x: (B, N, D) queries; y: (B, M, D) candidates.
        y_valid: optional (B, M) bool; invalid candidates (padding) are never chosen.
        max_elements: upper bound on B * chunk * M distances held at once.
        backend: how the neighbour is found: "torch" (chunked brute force, any device), "kdtree"
            (scipy's cKDTree on CPU: O(N log M), ~100x faster than brute force for thousands
            of 3D points on a CPU) or "auto" (kdtree for CPU tensors, torch elsewhere).
    Returns:
        sq_dist: (B, N) squared distance to the nearest neighbour (differentiable).
        idx: (B, N) int64 index of that neighbour in y. Where a batch element has no
            valid candidate the values are meaningless: callers must mask those out.
    """
    if x.dim() != 3 or y.dim() != 3 or x.shape[0] != y.shape[0] or x.shape[2] != y.shape[2]:
        raise ValueError(
            f"nearest_neighbors: expected (B, N, D) and (B, M, D), got {tuple(x.shape)} and {tuple(y.shape)}"
        )
    batch, num_x, _ = x.shape
    num_y = y.shape[1]
    if num_y == 0 or num_x == 0:
        return x.new_zeros(batch, num_x), torch.zeros(batch, num_x, dtype=torch.int64, device=x.device)
    if backend == "auto":
        backend = "kdtree" if x.device.type == "cpu" else "torch"
    if backend not in ("torch", "kdtree"):
        raise ValueError(f"nearest_neighbors: unknown backend {backend!r} (auto, torch or kdtree)")
    if backend == "kdtree":
        idx = kdtree_indices(x, y, y_valid)
        return _sq_dist_to(x, y, idx), idx
    chunk = max(1, max_elements // max(1, batch * num_y))
    idx_chunks = []
    with torch.no_grad():
        # Centre both sets on y's mean: the matmul form of cdist loses precision with |x|^2.
        centre = y.detach().mean(dim=1, keepdim=True)
        xd, yd = x.detach() - centre, y.detach() - centre
        invalid = None if y_valid is None else ~y_valid.unsqueeze(1)  # once, not per chunk
        for start in range(0, num_x, chunk):
            d = torch.cdist(xd[:, start : start + chunk], yd, compute_mode="use_mm_for_euclid_dist")
            if invalid is not None:
                d = d.masked_fill(invalid, float("inf"))
            idx_chunks.append(d.argmin(dim=2))
    idx = torch.cat(idx_chunks, dim=1)
    return _sq_dist_to(x, y, idx), idx


def _sq_dist_to(x: Tensor, y: Tensor, idx: Tensor) -> Tensor:
    """(B, N) squared distances from x to the points ``idx`` of y, differentiable w.r.t. both."""
    nearest = torch.gather(y, 1, idx.unsqueeze(-1).expand(-1, -1, y.shape[2]))
    return (x - nearest).pow(2).sum(-1)


KDTREE_LEAF_SIZE = 64


def kdtree_indices(x: Tensor, y: Tensor, y_valid: Tensor | None = None) -> Tensor:
    """(B, N) int64 index in y of each x point's nearest valid y point, by scipy's cKDTree (CPU,
    float64, no gradient). A batch element without valid candidates gets index 0 (mask it out).
    With one torch thread (usl-eval's side-by-side runs under ``OMP_NUM_THREADS=1``) and 3D points,
    with numba, the queries run as :mod:`usl.geometry.kdtree_search`'s compiled loop over the
    leaves of the two sets' trees (1.6x less CPU than the tree's own query on usl-eval's sets; the
    same nearest points, equidistant ones resolved to the lowest index); otherwise the tree's own
    query, on as many threads as torch uses. The tree is scipy's with other settings, measured on
    usl-eval's 10k-point sets (the same answer with any): leaves of 64 points, not 16, cut the
    query time by about 40% (fewer nodes visited); sliding-midpoint splits (``balanced_tree=False``)
    into cells not shrunk to their points (``compact_nodes=False``) cut it by another 25%."""
    xs, ys = x.detach().double().cpu().numpy(), y.detach().double().cpu().numpy()
    valid = None if y_valid is None else y_valid.cpu().numpy()
    out = np.zeros(x.shape[:2], dtype=np.int64)
    workers = torch.get_num_threads()
    blocked = workers == 1 and x.shape[2] == 3 and x.shape[1] > 0 and serves(x)
    for b in range(x.shape[0]):
        keep = np.arange(ys.shape[1]) if valid is None else np.flatnonzero(valid[b])
        if len(keep):
            tree = _kdtree(ys[b][keep])
            out[b] = keep[nearest_in_tree(_kdtree(xs[b]), tree) if blocked else tree.query(xs[b], workers=workers)[1]]
    return to_device(out, x.device)


def _kdtree(points: np.ndarray):
    from scipy.spatial import cKDTree

    return cKDTree(points, leafsize=KDTREE_LEAF_SIZE, compact_nodes=False, balanced_tree=False)


def chamfer_directions(
    x: Tensor,
    y: Tensor,
    x_valid: Tensor | None = None,
    y_valid: Tensor | None = None,
    max_elements: int = DEFAULT_MAX_ELEMENTS,
    backend: str = "torch",
) -> tuple[Tensor, Tensor]:
    """Squared nearest distances both ways, x -> y (B, N) and y -> x (B, M).

    Entries of invalid points, and of every point whose other set has no valid point,
    are set to zero so masked means can be taken directly. ``backend``: "torch" (as
    :func:`nearest_neighbors`) or "loop": on CPU tensors (with numba), both searches as one
    compiled brute-force loop with float64 distances (exact nearest points; for sets of a few
    hundred points it beats both the matrix-product search and a KD-tree), elsewhere "torch".
    """
    if backend not in ("torch", "loop"):
        raise ValueError(f"chamfer_directions: unknown backend {backend!r} (torch or loop)")
    x_valid = torch.ones(x.shape[:2], dtype=torch.bool, device=x.device) if x_valid is None else x_valid
    y_valid = torch.ones(y.shape[:2], dtype=torch.bool, device=y.device) if y_valid is None else y_valid
    if backend == "loop" and serves(x) and x.shape[1] and y.shape[1]:
        x_idx, y_idx = _loop_indices(x, y, x_valid, y_valid)
        x_to_y, y_to_x = _sq_dist_to(x, y, x_idx), _sq_dist_to(y, x, y_idx)
    else:
        x_to_y, _ = nearest_neighbors(x, y, y_valid, max_elements)
        y_to_x, _ = nearest_neighbors(y, x, x_valid, max_elements)
    keep_x = x_valid & y_valid.any(dim=1, keepdim=True)
    keep_y = y_valid & x_valid.any(dim=1, keepdim=True)
    return torch.where(keep_x, x_to_y, 0.0), torch.where(keep_y, y_to_x, 0.0)


def _loop_indices(x: Tensor, y: Tensor, x_valid: Tensor, y_valid: Tensor) -> tuple[Tensor, Tensor]:
    """(B, N) and (B, M) int64 nearest-valid-point indices both ways, by the compiled loop; both
    sets and their validity are read to the host at once, as one (B, N + M, D + 1) table."""
    points = torch.cat([x.detach(), y.detach().to(x.dtype)], dim=1)
    valid = torch.cat([x_valid, y_valid], dim=1).unsqueeze(-1).to(x.dtype)
    table = torch.cat([points, valid], dim=2).numpy()
    x_idx = np.empty(x.shape[:2], dtype=np.int64)
    y_idx = np.empty(y.shape[:2], dtype=np.int64)
    scratch_rows = max(x.shape[1], y.shape[1])
    _nearest_both_loop(
        table,
        x.shape[1],
        x_idx,
        y_idx,
        np.empty((x.shape[2], scratch_rows), dtype=np.float64),
        np.empty(scratch_rows, dtype=np.int64),
        np.empty(scratch_rows, dtype=np.float64),
    )
    return torch.from_numpy(x_idx), torch.from_numpy(y_idx)


@compiled
def _nearest_rows(points, queries, candidates, scratch, scratch_index, dists, out):  # pragma: no cover
    """out[i]: the first nearest valid point (last column != 0) among rows ``candidates`` (a
    range) to row ``queries[i]``, as an offset into the range; 0 when none is valid. The valid
    candidates are first copied to ``scratch`` (D, C) in float64; per query, their distances
    go to ``dists`` in a loop without branches (vectorized), then the first minimum is found."""
    dims = points.shape[1] - 1
    count = 0
    for j in candidates:
        if points[j, dims] != 0:
            for k in range(dims):
                scratch[k, count] = points[j, k]
            scratch_index[count] = j - candidates.start
            count += 1
    for i, q in enumerate(queries):
        for c in range(count):
            dists[c] = 0.0
        for k in range(dims):
            coordinate = np.float64(points[q, k])
            for c in range(count):
                diff = coordinate - scratch[k, c]
                dists[c] += diff * diff
        best, arg = np.inf, 0
        for c in range(count):
            if dists[c] < best:
                best, arg = dists[c], scratch_index[c]
        out[i] = arg


@compiled
def _nearest_both_loop(table, n, x_idx, y_idx, scratch, scratch_index, dists):  # pragma: no cover
    """Rows [0, n) of each table[b] are x, the rest y: nearest y of each x, and the reverse."""
    total = table.shape[1]
    for b in range(table.shape[0]):
        _nearest_rows(table[b], range(0, n), range(n, total), scratch, scratch_index, dists, x_idx[b])
        _nearest_rows(table[b], range(n, total), range(0, n), scratch, scratch_index, dists, y_idx[b])
