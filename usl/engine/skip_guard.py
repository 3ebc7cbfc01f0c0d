"""Stopping a run whose steps keep being skipped as non-finite.

A rare non-finite step (an outlier batch) is skipped and training goes on; many in a row mean
corrupt data or divergence, and a run that "finishes" that way only looks normal in metrics.csv.
Every rank skips together (the skip decision is all-reduced), so every rank stops together.
"""

from __future__ import annotations

from collections import deque

from usl.errors import UslError


class TooManySkippedSteps(UslError):
    """Training stopped: the recent steps were mostly non-finite."""


WINDOW = 20  # recent steps the skipped fraction is counted over: long enough that one outlier is no trend


class SkipGuard:
    """Counts skipped steps in a sliding window of the last ``window`` steps."""

    def __init__(self, max_fraction: float, window: int = WINDOW):
        self.max_fraction, self.window = max_fraction, window
        self.recent: deque[bool] = deque(maxlen=window)

    def update(self, skipped: bool, iteration: int) -> None:
        """Record one step; raise once more than ``max_fraction`` of a window's steps were skipped."""
        self.recent.append(bool(skipped))
        count = sum(self.recent)
        if count > self.max_fraction * self.window:
            raise TooManySkippedSteps(
                f"{count} of the last {len(self.recent)} steps (up to iteration {iteration}) had a non-finite loss "
                f"or gradient, more than train.max_skipped_fraction={self.max_fraction} of {self.window}; stopping. "
                "Check the data (usl-records validate), then lower optim.lr"
            )
