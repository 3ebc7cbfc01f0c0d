"""The IoU tracker on synthetic 2D detections with known identities: crossing objects of one category,
noise, misses, spurious blips and a short-lived object."""

from __future__ import annotations

import numpy as np
import pytest
from pycocotools import mask as mask_utils

from pipelines.scannet.masks import Detection
from pipelines.scannet.quality import tracking_quality
from pipelines.scannet.tracker import IouTracker, SourceIdTracker, Track, TrackerConfig

H, W = 100, 160
YY, XX = np.mgrid[0:H, 0:W] + 0.5


def disc(cx: float, cy: float, r: float) -> np.ndarray:
    return (XX - cx) ** 2 + (YY - cy) ** 2 < r * r


def rle(mask: np.ndarray) -> dict:
    return mask_utils.encode(np.asfortranarray(mask.astype(np.uint8)))


def scenario(num_frames: int = 100, noise: bool = False, seed: int = 0) -> list[list[tuple[Detection, int]]]:
    """Per frame: (detection, true id). A and B (same category) cross, A in front; C sits still;
    D lives 20 frames. With noise: jittered shapes, 10% misses, spurious one-frame blips."""
    rng = np.random.default_rng(seed)
    frames = []
    spurious_id = -1
    for t in range(num_frames):
        j = (lambda: rng.normal(0, 0.7)) if noise else (lambda: 0.0)
        dr = (lambda: rng.uniform(-1, 1)) if noise else (lambda: 0.0)
        a = disc(20 + 1.2 * t + j(), 40 + j(), 11 + dr())
        b = disc(140 - 1.2 * t + j(), 46 + j(), 11 + dr()) & ~a  # behind A: occluded while crossing
        c = disc(110 + 3 * np.sin(t / 9) + j(), 78 + j(), 12 + dr())
        objects = [(a, 1, 1), (b, 1, 2), (c, 2, 3)]
        if 30 <= t < 50:
            objects.append((disc(60 + j(), 80 + j(), 9 + dr()), 1, 4))
        if noise and rng.random() < 0.1:
            objects.append((disc(rng.uniform(0, W), rng.uniform(0, H), 5), 2, spurious_id))
            spurious_id -= 1
        dets = []
        for mask, category, true_id in objects:
            if mask.sum() < 25 or (noise and true_id > 0 and rng.random() < 0.1):
                continue  # too occluded to be detected, or missed
            dets.append((Detection(category, float(rng.uniform(0.6, 1.0)), rle(mask)), true_id))
        rng.shuffle(dets)
        frames.append(dets)
    return frames


def run(tracker, frames) -> list[tuple[int, int, int]]:
    observations = []
    for t, dets in enumerate(frames):
        ids = tracker.step(t, [d for d, _ in dets])
        observations += [(t, track_id, true_id) for track_id, (_, true_id) in zip(ids, dets, strict=True)]
    return observations


def majority_identity(track: Track, observations) -> int:
    ids = [true for _, tid, true in observations if tid == track.track_id]
    return max(set(ids), key=ids.count)


def test_clean_crossing_has_no_id_switch():
    tracker = IouTracker(TrackerConfig(min_track_frames=50))
    observations = run(tracker, scenario())
    quality = tracking_quality(observations)
    assert quality.id_switches == 0 and quality.purity == 1.0
    objects = tracker.objects()
    assert sorted(majority_identity(t, observations) for t in objects) == [1, 2, 3]  # D (20 frames) dropped
    assert all(len(t) >= 50 for t in objects)
    assert {t.category_id for t in objects} == {1, 2}


@pytest.mark.parametrize("seed", range(4))
def test_noisy_tracks_stay_pure(seed):
    """Tracks never mix identities; only the occluded object may fragment where it crosses behind A."""
    tracker = IouTracker(TrackerConfig(min_track_frames=50, max_missed=3))
    observations = run(tracker, scenario(noise=True, seed=seed))
    quality = tracking_quality(observations)
    assert quality.purity >= 0.95, quality.describe()
    assert quality.id_switches <= 3, quality.describe()
    kept = {majority_identity(t, observations) for t in tracker.objects()}
    assert {1, 3} <= kept <= {1, 2, 3}, quality.describe()


def test_without_tolerance_for_misses_tracks_break():
    """The noisy case needs max_missed: with 0 the same input fragments into more, shorter tracks."""
    frames = scenario(noise=True, seed=3)
    tolerant = tracking_quality(run(IouTracker(TrackerConfig(max_missed=3)), frames))
    strict = tracking_quality(run(IouTracker(TrackerConfig(max_missed=0)), frames))
    assert strict.id_switches > tolerant.id_switches


def test_a_track_survives_exactly_max_missed_frames():
    mask = rle(disc(50, 50, 10))
    for gap, expect_same in ((2, True), (3, False)):
        tracker = IouTracker(TrackerConfig(max_missed=2))
        first = tracker.step(0, [Detection(1, 0.9, mask)])
        for t in range(1, gap + 1):
            tracker.step(t, [])
        again = tracker.step(gap + 1, [Detection(1, 0.9, mask)])
        assert (first == again) is expect_same


def test_categories_do_not_match_unless_allowed():
    mask = rle(disc(50, 50, 10))
    frames = [[Detection(1, 0.9, mask)], [Detection(2, 0.95, mask)], [Detection(1, 0.9, mask)]]
    strict = IouTracker(TrackerConfig())
    assert [strict.step(t, d)[0] for t, d in enumerate(frames)] == [1, 2, 1]
    voting = IouTracker(TrackerConfig(match_across_categories=True))
    assert [voting.step(t, d)[0] for t, d in enumerate(frames)] == [1, 1, 1]
    assert voting.tracks[0].category_id == 1  # 0.9 + 0.9 outweighs 0.95


def test_hungarian_beats_greedy_matching():
    """Greedy matching would give detection 1 its best track (2, IoU 0.6) and leave detection 2 with
    nothing; the optimal assignment keeps both tracks (1 -> 1 at 0.33, 2 -> 2 at 0.45)."""

    def band(x0: int, x1: int) -> dict:
        mask = np.zeros((H, W), bool)
        mask[20:40, x0:x1] = True
        return rle(mask)

    tracker = IouTracker(TrackerConfig(iou_threshold=0.3))
    assert tracker.step(0, [Detection(1, 1.0, band(0, 40)), Detection(1, 1.0, band(30, 70))]) == [1, 2]
    assert tracker.step(1, [Detection(1, 1.0, band(20, 60)), Detection(1, 1.0, band(45, 85))]) == [1, 2]


def test_source_id_tracker_follows_given_identities():
    frames = scenario()
    for dets in frames:
        for k, (det, true_id) in enumerate(dets):
            dets[k] = (Detection(det.category_id, det.score, det.rle, source_id=true_id), true_id)
    tracker = SourceIdTracker(TrackerConfig(min_track_frames=50))
    observations = run(tracker, frames)
    assert all(track_id == true_id for _, track_id, true_id in observations)
    assert sorted(t.track_id for t in tracker.objects()) == [1, 2, 3]
    with pytest.raises(ValueError, match="source ids"):
        SourceIdTracker(TrackerConfig()).step(0, [Detection(1, 1.0, rle(disc(5, 5, 3)))])


def test_tracking_quality_counts():
    quality = tracking_quality([(0, 1, 7), (1, 1, 7), (2, 2, 7), (3, 2, 8), (4, 2, 8)])
    assert quality.id_switches == 1 and quality.num_tracks == 2 and quality.num_identities == 2
    assert quality.purity == pytest.approx(4 / 5)
