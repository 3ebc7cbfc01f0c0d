"""Assign predictions (anchors, proposals) to ground truth by IoU, and sample a balanced subset."""

from __future__ import annotations

from collections.abc import Sequence

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
        """``quality`` (..., G, P) IoUs -> (matched gt index (..., P), label (..., P)), e.g. a batch of
        images' (N, G, P) with absent ground truth rows padded with -1 (they match nothing).

        With no ground truth every prediction is background (index 0 is meaningless then).
        """
        if quality.shape[-2] == 0:
            zeros = quality.new_zeros(quality.shape[:-2] + quality.shape[-1:], dtype=torch.long)
            return zeros, zeros.clone()
        matched_quality, matches = quality.max(dim=-2)
        labels = torch.full_like(matches, self.labels[0])
        for threshold, label in zip(
            self.thresholds, self.labels[1:], strict=True
        ):  # where, not t[mask] = v: no device read
            labels = torch.where(matched_quality >= threshold, label, labels)
        if self.allow_low_quality_matches:
            best_per_gt = quality.max(dim=-1, keepdim=True).values
            # Ties count: every prediction achieving a gt's best IoU (> 0) is a match.
            is_best = ((quality == best_per_gt) & (best_per_gt > 0)).any(dim=-2)
            labels = torch.where(is_best, 1, labels)
        return matches, labels


def label_counts(labels: Sequence[Tensor]) -> list[tuple[int, int]]:
    """(foreground, background) counts of each image's labels, in one host read for them all."""
    if not labels:
        return []
    counts = torch.stack([torch.stack([(image == 1).sum(), (image == 0).sum()]) for image in labels])
    return [(int(positive), int(negative)) for positive, negative in counts.tolist()]


def subsample_labels(
    labels: Tensor, num_samples: int, positive_fraction: float, counts: tuple[int, int] | None = None
) -> tuple[Tensor, Tensor]:
    """Randomly pick at most ``num_samples`` of the labelled predictions, ideally a
    ``positive_fraction`` of them foreground (label 1), the rest background (label 0).

    ``counts``: the labels' ``label_counts`` when the caller has read them for a whole batch (the
    draws need them on the host; otherwise they are read here). Returns the indices of the sampled
    positives and negatives.
    """
    num_positive_labels, num_negative_labels = label_counts([labels])[0] if counts is None else counts
    positive = torch.nonzero_static(labels == 1, size=num_positive_labels).squeeze(1)
    negative = torch.nonzero_static(labels == 0, size=num_negative_labels).squeeze(1)
    num_positive = min(num_positive_labels, int(num_samples * positive_fraction))
    num_negative = min(num_negative_labels, num_samples - num_positive)
    positive = positive[torch.randperm(num_positive_labels, device=labels.device)[:num_positive]]
    negative = negative[torch.randperm(num_negative_labels, device=labels.device)[:num_negative]]
    return positive, negative


def subsample_labels_dense(labels: Tensor, num_samples: int, positive_fraction: float) -> Tensor:
    """:func:`subsample_labels` for each row of ``labels`` (N, P) at once, as labels: the sampled
    foreground 1, the sampled background 0, the rest -1 (ignored). A uniformly random subset of the
    same sizes, drawn by ranking random keys, so nothing is read back to the host."""
    keys = torch.rand(labels.shape, device=labels.device)
    positive, negative = labels == 1, labels == 0
    chosen_positive = positive & (_random_rank(positive, keys) < int(num_samples * positive_fraction))
    room = num_samples - chosen_positive.sum(dim=-1, keepdim=True)
    chosen_negative = negative & (_random_rank(negative, keys) < room)
    return torch.where(chosen_positive, 1, torch.where(chosen_negative, 0, IGNORE))


def _random_rank(member: Tensor, keys: Tensor) -> Tensor:
    """Each member's 0-based rank among its row's members by ``keys`` (non-members rank after them)."""
    order = torch.where(member, keys, 2.0).argsort(dim=-1)
    positions = torch.arange(member.shape[-1], device=member.device).expand_as(order)
    return torch.empty_like(order).scatter_(-1, order, positions)
