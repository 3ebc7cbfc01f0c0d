"""A loss weight that changes as training proceeds: piecewise linear in the iteration.

Why: l_dist moves the layout from anywhere in the frustum, and its gradient at the shape head is
one to two orders of magnitude above the gated l_xent's (measured on the tiny recipe). Early on that
is what is wanted; once the silhouettes overlap it drowns the pixel-wise shape signal. A schedule
on l_dist's factor keeps the paper's loss (``l_2D = f(t) l_dist + 1[IoU > 0.5] l_xent``) and only
shifts the balance between its two terms over time.
"""

from __future__ import annotations

from bisect import bisect_right
from dataclasses import dataclass
from itertools import pairwise


@dataclass(frozen=True)
class PiecewiseLinear:
    """``value(t)``: ``values[0]`` up to ``iters[0]``, linear between knots, ``values[-1]`` after.

    No knots means the constant 1 (the paper's unscheduled loss). Iterations count optimizer
    steps from 0, as the LR schedule does, so a resumed run continues on the same curve.
    """

    iters: tuple[int, ...] = ()  # knots: iterations, strictly increasing (none: the constant 1)
    values: tuple[float, ...] = ()  # the factor at each knot (>= 0), linear in between

    def __post_init__(self) -> None:
        if len(self.iters) != len(self.values):
            raise ValueError(
                f"schedule: {len(self.iters)} iters but {len(self.values)} values; give one value per knot"
            )
        if any(b <= a for a, b in pairwise(self.iters)):
            raise ValueError(f"schedule: iters must increase strictly, got {list(self.iters)}")
        if any(v < 0 for v in self.values):
            raise ValueError(f"schedule: values must be >= 0, got {list(self.values)}")

    def __call__(self, iteration: int) -> float:
        if not self.iters:
            return 1.0
        knot = bisect_right(self.iters, iteration)
        if knot == 0:
            return self.values[0]
        if knot == len(self.iters):
            return self.values[-1]
        (t0, t1), (v0, v1) = self.iters[knot - 1 : knot + 1], self.values[knot - 1 : knot + 1]
        return v0 + (v1 - v0) * (iteration - t0) / (t1 - t0)
