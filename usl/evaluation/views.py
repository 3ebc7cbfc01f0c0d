"""Which views of a scene are evaluation inputs, and which views score each object.

Input views: a deterministic pattern over a scene's view positions (``"first"``, ``"all"``,
``"every:K"``, ``"positions:0,5,9"``).

Other views ("Views" columns of the paper's tables), per input view and object, among the views
where that object's instance id appears (an object absent from a view has no true mask there, so
that (object, view) pair is skipped, never scored as 0):
* ``"all"``: every other view of the scene (Scene-Shapes, Hypersim);
* ``"furthest:F"``: the fraction F of the object's other views furthest in time (|view_id
  difference|) from the input, at least one -- the paper's ScanNet protocol ("the furthest 20% of
  frames in the track"), with F from ``data_specs/scannet.yaml`` tracking.eval_view_fraction;
* ``"auto"``: ``furthest:F`` when the dataset spec has ``tracking.eval_view_fraction``, else ``all``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from usl.errors import UslError


def select_input_views(pattern: str, num_views: int) -> list[int]:
    """Positions (0-based, within the scene) of the views used as model inputs."""
    kind, _, arg = pattern.partition(":")
    if kind == "first" and not arg:
        return [0] if num_views else []
    if kind == "all" and not arg:
        return list(range(num_views))
    if kind == "every" and arg.isdigit() and int(arg) > 0:
        return list(range(0, num_views, int(arg)))
    if kind == "positions" and arg:
        try:
            positions = sorted({int(p) for p in arg.split(",")})
        except ValueError:
            positions = []
        if positions and positions[0] >= 0:
            return [p for p in positions if p < num_views]
    raise UslError(f"input views {pattern!r}: expected first, all, every:K (K > 0) or positions:P1,P2,...")


class ViewSelection(Protocol):
    """Picks, per object of an input view, the other views that score it."""

    def __call__(
        self, input_position: int, view_ids: Sequence[int], presence: Mapping[int, Sequence[int]]
    ) -> dict[int, list[int]]:
        """``presence``: instance id -> positions where it is visible; returns instance id -> positions."""
        ...


@dataclass(frozen=True)
class AllOtherViews:
    """Every other view in which the object appears."""

    def __call__(
        self, input_position: int, view_ids: Sequence[int], presence: Mapping[int, Sequence[int]]
    ) -> dict[int, list[int]]:
        return {iid: [p for p in positions if p != input_position] for iid, positions in presence.items()}


@dataclass(frozen=True)
class FurthestFraction:
    """The ``fraction`` of each object's other views furthest in time from the input (at least one)."""

    fraction: float

    def __post_init__(self) -> None:
        if not 0.0 < self.fraction <= 1.0:
            raise UslError(f"other views: the fraction must be in (0, 1], got {self.fraction}")

    def __call__(
        self, input_position: int, view_ids: Sequence[int], presence: Mapping[int, Sequence[int]]
    ) -> dict[int, list[int]]:
        t0 = view_ids[input_position]
        out = {}
        for iid, positions in presence.items():
            others = [p for p in positions if p != input_position]
            # Furthest first; equal distances prefer the later view, so the order is total.
            others.sort(key=lambda p: (abs(view_ids[p] - t0), view_ids[p]), reverse=True)
            keep = math.ceil(self.fraction * len(others) - 1e-9)
            out[iid] = sorted(others[: max(keep, 1) if others else 0])
        return out


def view_selection(pattern: str, spec: Mapping[str, Any] | None = None) -> ViewSelection:
    """Parse an other-views pattern (see module doc); ``spec`` resolves ``"auto"``."""
    kind, _, arg = pattern.partition(":")
    if kind == "all" and not arg:
        return AllOtherViews()
    if kind == "furthest" and arg:
        try:
            return FurthestFraction(float(arg))
        except ValueError:
            pass
    if kind == "auto" and not arg:
        fraction = ((spec or {}).get("tracking") or {}).get("eval_view_fraction")
        return FurthestFraction(float(fraction)) if fraction else AllOtherViews()
    raise UslError(f"other views {pattern!r}: expected all, furthest:F (0 < F <= 1) or auto")
