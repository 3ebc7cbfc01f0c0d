"""Tracking 2D instance masks across a video into objects (paper Sec. 4.3: "a simple mask IoU heuristic").

Each processed frame's detections are matched to the active tracks by the Hungarian algorithm on
``1 - mask IoU`` (computed on RLE by pycocotools), only between equal categories unless configured
otherwise, and a match needs IoU >= ``iou_threshold``. A track survives ``max_missed`` processed
frames without a match. When a warp is given, a track's last mask is also compared after warping it
into the current frame (depth + relative pose), and the better of the two IoUs counts.
Tracks with at least ``min_track_frames`` observations become objects.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from pycocotools import mask as mask_utils
from scipy.optimize import linear_sum_assignment

from .masks import RLE, Detection


class Warp(Protocol):
    """Moves masks of an earlier frame into the current one (``warp.DepthWarp``)."""

    def covered(self, source: int, height: int, width: int) -> RLE | None:
        """Current pixels on which warping from ``source`` is defined; None if it is not possible."""
        ...

    def warp(self, source: int, rle: RLE) -> RLE | None:
        """The mask of frame ``source`` as seen from the current frame."""
        ...


FORBIDDEN = 1e6


@dataclass(frozen=True)
class TrackerConfig:
    iou_threshold: float = 0.5
    max_missed: int = 3  # processed frames a track may go unmatched and still continue
    min_track_frames: int = 50  # observations (processed frames) a track needs to become an object
    match_across_categories: bool = False  # True: any category may match; a track's category is then voted

    def __post_init__(self) -> None:
        if not 0.0 < self.iou_threshold <= 1.0:
            raise ValueError(f"iou_threshold must lie in (0, 1], got {self.iou_threshold}")
        if self.max_missed < 0 or self.min_track_frames < 1:
            raise ValueError("max_missed must be >= 0 and min_track_frames >= 1")


@dataclass
class Track:
    track_id: int
    frames: list[int] = field(default_factory=list)
    detections: list[Detection] = field(default_factory=list)
    missed: int = 0

    def add(self, frame: int, detection: Detection) -> None:
        self.frames.append(frame)
        self.detections.append(detection)
        self.missed = 0

    @property
    def last_frame(self) -> int:
        return self.frames[-1]

    @property
    def last_rle(self) -> RLE:
        return self.detections[-1].rle

    @property
    def category_id(self) -> int:
        """Score-weighted vote over the track's detections (ties: the smaller category id)."""
        votes: dict[int, float] = defaultdict(float)
        for det in self.detections:
            votes[det.category_id] += det.score
        return min(votes, key=lambda c: (-votes[c], c))

    def __len__(self) -> int:
        return len(self.frames)


def iou_matrix(detections: Sequence[RLE], tracks: Sequence[RLE]) -> np.ndarray:
    """(n_det, n_track) mask IoU, computed on RLE."""
    if not detections or not tracks:
        return np.zeros((len(detections), len(tracks)))
    return np.asarray(mask_utils.iou(list(detections), list(tracks), [0] * len(tracks)), dtype=np.float64).reshape(
        len(detections), len(tracks)
    )


class IouTracker:
    def __init__(self, config: TrackerConfig):
        self.config = config
        self._tracks: list[Track] = []
        self._active: list[Track] = []

    def step(self, frame: int, detections: Sequence[Detection], warp: Warp | None = None) -> list[int]:
        """Assign every detection of ``frame`` to a track (a new one if nothing matches); returns track ids."""
        active = self._active
        iou = self._ious(detections, active, warp)
        if not self.config.match_across_categories:
            same = np.array([[d.category_id == t.detections[0].category_id for t in active] for d in detections], bool)
            iou = np.where(same.reshape(iou.shape), iou, 0.0)
        cost = np.where(iou >= self.config.iou_threshold, 1.0 - iou, FORBIDDEN)
        rows, cols = linear_sum_assignment(cost) if cost.size else (np.zeros(0, int), np.zeros(0, int))
        assigned: dict[int, Track] = {
            int(r): active[int(c)] for r, c in zip(rows, cols, strict=True) if cost[r, c] < FORBIDDEN
        }
        ids = []
        for k, det in enumerate(detections):
            track = assigned.get(k)
            if track is None:
                track = Track(len(self._tracks) + 1)
                self._tracks.append(track)
                active.append(track)
            track.add(frame, det)
            ids.append(track.track_id)
        matched = {t.track_id for t in assigned.values()} | set(ids)
        for track in active:
            if track.track_id not in matched:
                track.missed += 1
        self._active = [t for t in active if t.missed <= self.config.max_missed]
        return ids

    def _ious(self, detections: Sequence[Detection], active: Sequence[Track], warp: Warp | None) -> np.ndarray:
        det_rles = [d.rle for d in detections]
        iou = iou_matrix(det_rles, [t.last_rle for t in active])
        if warp is None or not detections:
            return iou
        by_source: dict[int, list[int]] = defaultdict(list)
        for j, track in enumerate(active):
            by_source[track.last_frame].append(j)
        height, width = det_rles[0]["size"]
        for source, columns in by_source.items():
            covered = warp.covered(source, height, width)
            if covered is None:
                continue
            # compare only where the warp is defined: detections clipped to the covered pixels
            clipped = [mask_utils.merge([rle, covered], intersect=True) for rle in det_rles]
            moved = [warp.warp(source, active[j].last_rle) for j in columns]
            iou[:, columns] = np.maximum(iou[:, columns], iou_matrix(clipped, moved))
        return iou

    @property
    def active_frames(self) -> set[int]:
        """Frames holding the last mask of some active track (what a warp still needs)."""
        return {t.last_frame for t in self._active}

    @property
    def tracks(self) -> list[Track]:
        return list(self._tracks)

    def objects(self) -> list[Track]:
        """Tracks long enough to become objects, in order of first appearance."""
        return [t for t in self._tracks if len(t) >= self.config.min_track_frames]


class SourceIdTracker:
    """Tracks given by the mask source's own identities (ScanNet instance ids): no matching at all."""

    def __init__(self, config: TrackerConfig):
        self.config = config
        self._by_source: dict[int, Track] = {}

    def step(self, frame: int, detections: Sequence[Detection], warp: Warp | None = None) -> list[int]:
        ids = []
        for det in detections:
            if det.source_id is None:
                raise ValueError("the source-ids tracker needs detections that carry source ids")
            track = self._by_source.setdefault(det.source_id, Track(int(det.source_id)))
            track.add(frame, det)
            ids.append(track.track_id)
        return ids

    @property
    def active_frames(self) -> set[int]:
        return set()

    @property
    def tracks(self) -> list[Track]:
        return sorted(self._by_source.values(), key=lambda t: t.frames[0])

    def objects(self) -> list[Track]:
        return [t for t in self.tracks if len(t) >= self.config.min_track_frames]
