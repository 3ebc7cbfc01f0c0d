"""scripts/experiments/placement_chamfer.py: the alignments it scores, against brute-force distances (scipy's cdist)."""

from __future__ import annotations

import numpy as np
import placement_chamfer
import torch
from scipy.spatial.distance import cdist


def _chamfer(a: np.ndarray, b: np.ndarray) -> float:
    squared = cdist(a, b, "sqeuclidean")  # every pair, not the kd-tree usl's Chamfer uses on CPU
    return float(squared.min(1).mean() + squared.min(0).mean())


def test_alignments_remove_the_translation_and_only_the_depth_part_of_it():
    rng = np.random.default_rng(0)
    true = rng.normal(size=(2, 400, 3)) * [0.4, 0.3, 0.2]
    squashed = true[:, rng.permutation(400)] * [1.0, 0.8, 1.0]  # another shape, same centroid
    shift = np.array([[[0.3, -0.2, 0.5]], [[0.0, 0.1, -0.4]]])
    pred = squashed + shift
    scores = placement_chamfer.aligned_scores(torch.tensor(pred), torch.tensor(true))
    centred = pred - pred.mean(1, keepdims=True) + true.mean(1, keepdims=True)
    depth_moved = pred.copy()
    depth_moved[..., 2] += (true.mean(1) - pred.mean(1))[:, None, 2]
    for name, points in (("as predicted", pred), ("centroids aligned", centred), ("depth aligned", depth_moved)):
        want = [_chamfer(points[b], true[b]) for b in range(2)]
        np.testing.assert_allclose(scores[name][0].numpy(), want, rtol=1e-6)
    assert (scores["centroids aligned"][0] < scores["depth aligned"][0]).all()
    assert (scores["depth aligned"][0] < scores["as predicted"][0]).all()
