"""Assign predictions (anchors, proposals) to ground truth by IoU, and sample a balanced subset."""

from __future__ import annotations

from typing import Sequence

import torch

Tensor = torch.Tensor

IGNORE = -1


class Matcher:
    """Match each prediction to its highest-IoU ground-truth box and label it by IoU band.

    ``thresholds`` split ``[0, 1]`` into bands, ``labels`` give each band's label
    (1 foreground, 0 background, -1 ignore): e.g. the RPN's ``(0.3, 0.7)`` with
    ``(0, -1, 1)``. A band includes its lower threshold. With
    ``allow_low_quality_matches``, each ground truth's best prediction(s) are made
    foreground even below the top threshold, so every object gets an anchor.
    """

    def __init__(self, thresholds: Sequence[float], labels: Sequence[int], allow_low_quality_matches: bool = False):
        if len(labels) != len(thresholds) + 1:
            raise ValueError(f"need len(thresholds) + 1 labels, got {list(thresholds)} and {list(labels)}")
        if list(thresholds) != sorted(thresholds):
            raise ValueError(f"thresholds must increase, got {list(thresholds)}")
        if any(label not in (IGNORE, 0, 1) for label in labels):
            raise ValueError(f"labels must be -1, 0 or 1, got {list(labels)}")
        self.thresholds = [float(t) for t in thresholds]
        self.labels = [int(label) for label in labels]
        self.allow_low_quality_matches = allow_low_quality_matches

    def __call__(self, quality: Tensor) -> tuple[Tensor, Tensor]:
        """``quality`` (G, P) IoUs -> (matched gt index (P,), label (P,)).

        With no ground truth every prediction is background (index 0 is meaningless then).
        """
        num_predictions = quality.shape[1]
        if quality.shape[0] == 0:
            zeros = quality.new_zeros(num_predictions, dtype=torch.long)
            return zeros, zeros.clone()
        matched_quality, matches = quality.max(dim=0)
        labels = torch.full_like(matches, self.labels[0])
        for threshold, label in zip(self.thresholds, self.labels[1:]):
            labels[matched_quality >= threshold] = label
        if self.allow_low_quality_matches:
            best_per_gt = quality.max(dim=1, keepdim=True).values
            # Ties count: every prediction achieving a gt's best IoU (> 0) is a match.
            is_best = ((quality == best_per_gt) & (best_per_gt > 0)).any(dim=0)
            labels[is_best] = 1
        return matches, labels


def subsample_labels(labels: Tensor, num_samples: int, positive_fraction: float) -> tuple[Tensor, Tensor]:
    """Randomly pick at most ``num_samples`` of the labelled predictions, ideally a
    ``positive_fraction`` of them foreground (label 1), the rest background (label 0).

    Returns the indices of the sampled positives and negatives.
    """
    positive = torch.nonzero(labels == 1).squeeze(1)
    negative = torch.nonzero(labels == 0).squeeze(1)
    num_positive = min(positive.numel(), int(num_samples * positive_fraction))
    num_negative = min(negative.numel(), num_samples - num_positive)
    positive = positive[torch.randperm(positive.numel(), device=labels.device)[:num_positive]]
    negative = negative[torch.randperm(negative.numel(), device=labels.device)[:num_negative]]
    return positive, negative
