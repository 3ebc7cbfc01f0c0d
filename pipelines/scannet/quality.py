"""Tracker quality against known identities (ScanNet's consistent instance ids, or synthetic truth)."""

from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Iterable
from dataclasses import dataclass
from itertools import pairwise


@dataclass(frozen=True)
class TrackingQuality:
    purity: float  # share of tracked detections whose true identity is their track's majority identity
    id_switches: int  # times a true identity's track id changes between consecutive observations
    num_tracks: int
    num_identities: int

    def describe(self) -> str:
        return (
            f"purity {self.purity:.4f}, {self.id_switches} id switch(es), "
            f"{self.num_tracks} track(s) for {self.num_identities} identit(ies)"
        )


def tracking_quality(observations: Iterable[tuple[int, int, int]]) -> TrackingQuality:
    """Quality from ``(frame, track_id, true_id)`` triples, one per tracked detection.

    Purity weighs tracks by length. An id switch is counted whenever a true identity, followed in
    frame order, is assigned a different track than at its previous observation (MOT's IDSW, which
    also counts a track broken into two).
    """
    by_track: dict[int, Counter] = defaultdict(Counter)
    by_truth: dict[int, list[tuple[int, int]]] = defaultdict(list)
    for frame, track_id, true_id in observations:
        by_track[track_id][true_id] += 1
        by_truth[true_id].append((frame, track_id))
    total = sum(sum(c.values()) for c in by_track.values())
    majority = sum(c.most_common(1)[0][1] for c in by_track.values())
    switches = 0
    for seq in by_truth.values():
        seq.sort()
        switches += sum(1 for (_, a), (_, b) in pairwise(seq) if a != b)
    return TrackingQuality(majority / total if total else 1.0, switches, len(by_track), len(by_truth))
