"""Choosing the M - 1 other views of a training sample (paper Sec. 3.4 and 4.3)."""
from __future__ import annotations

from typing import Sequence

import numpy as np

STRATEGIES = ("uniform", "time_distance")


def sample_other_views(
    view_ids: Sequence[int],
    instance_ids: Sequence[np.ndarray],
    input_position: int,
    objects: np.ndarray,
    count: int,
    strategy: str,
    rng: np.random.Generator,
) -> list[int]:
    """Positions (within the scene) of ``count`` views other than the input that show its objects.

    Candidates are the views sharing at least one of ``objects`` (instance ids) with the input.
    ``uniform`` draws them with equal probability; ``time_distance`` with probability
    proportional to ``|view_id - input view_id|`` (the paper's ScanNet sampling: distant frames
    of a video show the object from more different directions), without replacement. With
    fewer candidates than ``count`` all of them are returned (the sample has fewer views rather
    than repeated ones); none gives an empty list (the sample has only its input view).
    """
    if strategy not in STRATEGIES:
        raise ValueError(f"unknown view sampling {strategy!r}; choose from {STRATEGIES}")
    if count <= 0 or len(objects) == 0:
        return []
    candidates = [
        p for p in range(len(view_ids)) if p != input_position and np.isin(instance_ids[p], objects).any()
    ]
    if not candidates:
        return []
    if strategy == "uniform":
        weights = np.ones(len(candidates))
    else:
        weights = np.abs(np.asarray([view_ids[p] for p in candidates], dtype=np.float64) - view_ids[input_position])
        weights = np.maximum(weights, 1e-9)  # a duplicated view id would otherwise never be drawn
    if len(candidates) <= count:
        return candidates
    chosen = rng.choice(len(candidates), size=count, replace=False, p=weights / weights.sum())
    return [candidates[i] for i in chosen]
