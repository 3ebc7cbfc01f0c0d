"""3D shape metrics of Mesh R-CNN (Chamfer-L2, precision / recall / F1 at distance thresholds)."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from usl.geometry.meshes import Meshes
from usl.geometry.nearest import DEFAULT_MAX_ELEMENTS, kdtree_indices, lengths_to_mask, nearest_neighbors
from usl.geometry.sampling import sample_points_from_meshes

Tensor = torch.Tensor

# Mesh R-CNN evaluates on 10k points sampled per mesh.
NUM_EVAL_SAMPLES = 10_000


def chamfer_f1(
    pred_points: Tensor,
    gt_points: Tensor,
    pred_lengths: Tensor | None = None,
    gt_lengths: Tensor | None = None,
    thresholds: float | Sequence[float] = 0.1,
    max_elements: int = DEFAULT_MAX_ELEMENTS,
    backend: str = "auto",
) -> dict[str, Tensor]:
    """Per-pair Chamfer-L2 and precision / recall / F1 (x100) between two batched point sets.

    As in Mesh R-CNN: with nearest Euclidean distances d(p -> gt) and d(g -> pred),
    ``Chamfer-L2 = mean d(p -> gt)^2 + mean d(g -> pred)^2``; at threshold t,
    ``Precision = 100 * mean[d(p -> gt) < t]``, ``Recall = 100 * mean[d(g -> pred) < t]``,
    ``F1 = 2 P R / (P + R)`` (0 when both are 0). Units follow the points (metres here,
    so the paper's F1@0.1 m is ``thresholds=0.1``); no rescaling is applied.

    Args:
        pred_points: (B, N, 3); gt_points: (B, M, 3); optional lengths for padding.
        backend: "torch" (chunked brute force, any device), "kdtree" (scipy's cKDTree, CPU) or
            "auto": kdtree for CPU tensors, where brute force on 10k x 10k points per pair is
            ~100x slower, torch elsewhere. Metrics need no gradient, so both give the same numbers.
    Returns:
        dict of (B,) tensors: "Chamfer-L2" and, per threshold t, "Precision@t",
        "Recall@t", "F1@t" (t formatted with ``f"{t:g}"``, e.g. "F1@0.1").
    """
    pred_valid = None if pred_lengths is None else lengths_to_mask(pred_lengths, pred_points.shape[1])
    gt_valid = None if gt_lengths is None else lengths_to_mask(gt_lengths, gt_points.shape[1])
    if backend == "auto":
        backend = "kdtree" if pred_points.device.type == "cpu" else "torch"
    if backend not in ("torch", "kdtree"):
        raise ValueError(f"chamfer_f1: unknown backend {backend!r} (auto, torch or kdtree)")
    with torch.no_grad():
        if backend == "kdtree":
            pred_to_gt = _kdtree_sq_distances(pred_points, gt_points, gt_valid)
            gt_to_pred = _kdtree_sq_distances(gt_points, pred_points, pred_valid)
        else:
            pred_to_gt = nearest_neighbors(pred_points, gt_points, gt_valid, max_elements)[0]
            gt_to_pred = nearest_neighbors(gt_points, pred_points, pred_valid, max_elements)[0]
    pred_w = _weights(pred_points, pred_valid)
    gt_w = _weights(gt_points, gt_valid)
    out = {"Chamfer-L2": (pred_to_gt * pred_w).sum(1) + (gt_to_pred * gt_w).sum(1)}
    for t in [thresholds] if isinstance(thresholds, (int, float)) else thresholds:
        precision = 100.0 * ((pred_to_gt < t * t) * pred_w).sum(1)
        recall = 100.0 * ((gt_to_pred < t * t) * gt_w).sum(1)
        f1 = torch.where(precision + recall > 0, 2 * precision * recall / (precision + recall).clamp(min=1e-12), 0.0)
        out[f"Precision@{t:g}"], out[f"Recall@{t:g}"], out[f"F1@{t:g}"] = precision, recall, f1
    return out


def _kdtree_sq_distances(x: Tensor, y: Tensor, y_valid: Tensor | None) -> Tensor:
    """Squared distance from each point of x to its nearest valid point of y (float64), per batch item."""
    idx = kdtree_indices(x, y, y_valid)
    xs, ys = x.detach().double(), y.detach().double()
    nearest = torch.gather(ys, 1, idx.to(ys.device).unsqueeze(-1).expand(-1, -1, ys.shape[2]))
    sq = (xs - nearest).pow(2).sum(-1)
    if y_valid is not None:  # no candidate: 0, as before
        sq = torch.where(y_valid.any(1, keepdim=True).to(sq.device), sq, 0.0)
    return sq.to(dtype=x.dtype, device=x.device)


def _weights(points: Tensor, valid: Tensor | None) -> Tensor:
    """(B, N) weights averaging over the valid points of each set."""
    if valid is None:
        return torch.full(points.shape[:2], 1.0 / max(points.shape[1], 1), dtype=points.dtype, device=points.device)
    valid = valid.to(points.dtype)
    return valid / valid.sum(1, keepdim=True).clamp(min=1)


def compare_meshes(
    pred: Meshes,
    gt: Meshes,
    num_samples: int = NUM_EVAL_SAMPLES,
    thresholds: float | Sequence[float] = 0.1,
    generator: torch.Generator | None = None,
) -> dict[str, Tensor]:
    """Mesh R-CNN's mesh comparison: sample ``num_samples`` points per mesh, then ``chamfer_f1``.

    ``pred`` and ``gt`` are aligned batches (mesh i of one against mesh i of the other),
    both in the same frame (the input view's camera frame for the paper's evaluation).
    """
    if len(pred) != len(gt):
        raise ValueError(f"compare_meshes: {len(pred)} predicted meshes but {len(gt)} ground-truth meshes")
    with torch.no_grad():
        pred_points = sample_points_from_meshes(pred, num_samples, generator)
        gt_points = sample_points_from_meshes(gt, num_samples, generator)
    return chamfer_f1(pred_points, gt_points, thresholds=thresholds)
