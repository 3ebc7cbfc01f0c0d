"""Input-view and other-view selection (incl. the paper's ScanNet "furthest 20% of the track")."""

from __future__ import annotations

import pytest

from usl.errors import UslError
from usl.evaluation.views import AllOtherViews, FurthestFraction, select_input_views, view_selection


def test_input_view_patterns():
    assert select_input_views("first", 5) == [0]
    assert select_input_views("all", 3) == [0, 1, 2]
    assert select_input_views("every:2", 5) == [0, 2, 4]
    assert select_input_views("positions:4,1,9", 5) == [1, 4]
    assert select_input_views("first", 0) == []
    for bad in ("every:0", "every:x", "positions:", "positions:-1", "last", "all:2"):
        with pytest.raises(UslError, match="input views"):
            select_input_views(bad, 5)


def test_all_other_views_skips_input_and_absent_views():
    presence = {7: [0, 1, 3], 8: [0]}
    assert AllOtherViews()(0, [0, 1, 2, 3], presence) == {7: [1, 3], 8: []}


def test_furthest_fraction_picks_the_far_end_of_each_track():
    view_ids = list(range(0, 200, 10))  # 20 frames, view_id = 10 * position
    track = list(range(2, 17))  # object seen in positions 2..16
    chosen = FurthestFraction(0.2)(5, view_ids, {1: track})[1]
    # 14 other frames -> ceil(2.8) = 3 furthest in time from position 5: positions 16, 15, 14.
    assert chosen == [14, 15, 16]
    # Both sides count: from the middle, the furthest frames are at either end (ties: the later one).
    assert FurthestFraction(0.2)(9, view_ids, {1: track})[1] == [2, 15, 16]
    # At least one view whenever the object appears elsewhere; none otherwise.
    assert FurthestFraction(0.01)(5, view_ids, {1: [4, 5]})[1] == [4]
    assert FurthestFraction(0.2)(5, view_ids, {1: [5]})[1] == []


def test_view_selection_from_spec():
    assert isinstance(view_selection("auto", {"tracking": {"eval_view_fraction": 0.2}}), FurthestFraction)
    assert view_selection("auto", {"tracking": {"eval_view_fraction": 0.2}}).fraction == 0.2
    assert isinstance(view_selection("auto", {}), AllOtherViews)
    assert view_selection("furthest:0.5").fraction == 0.5
    for bad in ("furthest:0", "furthest:1.5", "furthest:x", "some"):
        with pytest.raises(UslError, match="other views"):
            view_selection(bad)
