"""One scan -> one record scene, in two streaming passes over its frames.

Pass 1 reads poses, depth and the mask source frame by frame and feeds the tracker; it keeps only
RLE masks and a few depth maps for warping. Which tracks are long enough is known only at the end,
so pass 2 reads again the frames that hold an object's observation and encodes them (image as
stored when no resize is needed, depth as 16-bit PNG). Nothing decoded outlives its frame, and
encoded rows go to the build's ``frame_sink`` one by one, so memory does not grow with scan length.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
from pycocotools import mask as mask_utils

from pipelines.common import frame_sink
from usl.errors import UslError
from usl.records import SceneRecord, Skip, encode_depth, frame_row, make_instance

from .exported import ExportedScan
from .grid import OutputGrid
from .masks import Detection, FrameView, MaskSource, ScanMasks
from .scan import Scan, rigid_pose
from .sens import SensScan
from .tracker import IouTracker, SourceIdTracker, Track, TrackerConfig
from .warp import DepthWarp

SKIP_POSE = "invalid camera pose (non-finite, e.g. -inf for lost tracking, or not rigid)"
SKIP_DEPTH = "empty depth"
SKIP_NO_OBJECT = "no object track in frame"
SKIP_NO_DETECTIONS = "mask source gave no detections for this scan"
SKIP_VANISHED = "object mask empty at the output resolution (instance left out of that frame)"


def open_scan(scene_dir: Path, scene_id: str) -> Scan:
    """Open ``<scene_dir>/<scene_id>.sens`` if present, else the exported frame folders there."""
    scene_dir = Path(scene_dir)
    sens = scene_dir / f"{scene_id}.sens"
    if sens.is_file():
        return SensScan(sens, scene_id)
    if (scene_dir / "color").is_dir():
        return ExportedScan(scene_dir, scene_id)
    raise UslError(f"{scene_dir}: neither {sens.name} nor exported color/ depth/ pose/ intrinsic/ folders")


@dataclass(frozen=True)
class ConvertOptions:
    stride: int = 10  # process every stride-th frame of the scan
    size: tuple[int, int] | None = (640, 480)  # output (width, height); None keeps the colour resolution
    jpeg_quality: int = 95  # only when images must be re-encoded (resized or raw colour)
    store_depth: bool = True
    min_score: float = 0.5  # detections below this confidence are ignored
    warp: str = "auto"  # "auto": warp masks with depth+pose when stride > 1; "on"; "off"
    depth_tolerance: float = 0.2  # metres: warp lookups need source depth to agree this well
    tracker: TrackerConfig = field(default_factory=TrackerConfig)
    use_source_ids: bool = False  # tracks = the mask source's own ids (ScanNet labels), no IoU matching

    def __post_init__(self) -> None:
        if self.stride < 1:
            raise ValueError(f"stride must be >= 1, got {self.stride}")
        if self.warp not in ("auto", "on", "off"):
            raise ValueError(f"warp must be auto, on or off, got {self.warp!r}")
        if self.size is not None and min(self.size) < 1:
            raise ValueError(f"output size must be positive, got {self.size}")
        if not 1 <= self.jpeg_quality <= 100:
            raise ValueError(f"--jpeg-quality must lie in 1..100, got {self.jpeg_quality}")

    @property
    def warps(self) -> bool:
        return self.warp == "on" or (self.warp == "auto" and self.stride > 1)


@dataclass(frozen=True)
class ScanUnit:
    """A build unit: one scan, picklable for the build driver's worker processes."""

    scene_id: str
    scene_dir: str
    masks: MaskSource
    options: ConvertOptions


@dataclass
class TrackedScan:
    """What pass 1 leaves: tracks (RLE at the mask source's resolution), valid frames with poses, skips."""

    tracks: list[Track]
    objects: list[Track]
    poses: dict[int, np.ndarray]  # processed, valid frames in order -> cam_to_world
    skips: Counter = field(default_factory=Counter)
    num_detections: int = 0


def frame_detections(
    masks: ScanMasks, scan: Scan, index: int, min_score: float, size: list[int | None]
) -> list[Detection]:
    """The source's detections of one frame that are confident enough.

    Masks stay at the source's resolution (tracking compares RLEs there, no resampling); all masks
    of a scan must share one size, recorded in ``size`` ([height, width], filled on first use).
    """
    out = []
    for det in masks.detect(FrameView(index, partial(scan.color, index))):
        if det.score < min_score:
            continue
        if size[0] is None:
            size[:] = det.rle["size"]
        elif list(det.rle["size"]) != size:
            raise UslError(
                f"{scan.path}: frame {index}: the mask source gave a {det.rle['size']} mask after "
                f"{size} ones; masks of one scan must share a size"
            )
        out.append(det)
    return out


def track_scan(scan: Scan, masks: ScanMasks, grid: OutputGrid, options: ConvertOptions) -> TrackedScan:
    """Pass 1: stream the processed frames through the tracker."""
    tracker = SourceIdTracker(options.tracker) if options.use_source_ids else IouTracker(options.tracker)
    has_depth = scan.calibration.has_depth
    warps = options.warps and has_depth
    warp = DepthWarp(grid.K, grid.width, grid.height, options.depth_tolerance) if warps else None
    poses: dict[int, np.ndarray] = {}
    skips: Counter = Counter()
    num_detections = 0
    mask_size: list[int | None] = [None, None]
    for index in scan.frame_indices[:: options.stride]:
        pose = rigid_pose(scan.pose(index))
        if pose is None:
            skips[SKIP_POSE] += 1
            continue
        depth = scan.depth(index) if has_depth else None
        if has_depth and depth is None:
            skips[SKIP_DEPTH] += 1
            continue
        detections = frame_detections(masks, scan, index, options.min_score, mask_size)
        num_detections += len(detections)
        if warp is not None:
            warp.add_frame(index, grid.depth(depth), pose)
        tracker.step(index, detections, warp)
        if warp is not None:
            warp.retain(tracker.active_frames)
        poses[index] = pose
    return TrackedScan(tracker.tracks, tracker.objects(), poses, skips, num_detections)


def scene_frames(scan: Scan, tracked: TrackedScan, grid: OutputGrid, options: ConvertOptions) -> Iterator[dict]:
    """Pass 2: one record row per frame that holds at least one object observation, in frame order."""
    by_frame: dict[int, list[tuple[int, int, dict]]] = defaultdict(list)
    for track in tracked.objects:
        category = track.category_id
        for frame, det in zip(track.frames, track.detections, strict=True):
            by_frame[frame].append((track.track_id, category, det.rle))
    for index, pose in tracked.poses.items():
        observations = sorted(by_frame.get(index, []), key=lambda o: o[0])
        masks = [(iid, cat, grid.mask(mask_utils.decode(rle))) for iid, cat, rle in observations]
        kept = [(iid, cat, mask) for iid, cat, mask in masks if mask.any()]
        tracked.skips[SKIP_VANISHED] += len(masks) - len(kept)
        if not kept:
            tracked.skips[SKIP_NO_OBJECT] += 1
            continue
        depth = grid.depth(scan.depth(index))
        instances = [make_instance(iid, cat, mask.astype(bool), depth) for iid, cat, mask in kept]
        depth_png = encode_depth(depth) if options.store_depth and depth is not None else None
        image = grid.image(scan, index, options.jpeg_quality)
        yield frame_row(scan.scene_id, index, image, grid.K, pose, instances, grid.height, grid.width, depth_png)


def convert_scan(
    scan: Scan,
    masks: MaskSource,
    options: ConvertOptions,
    skips: Counter | None = None,
    provenance: dict[str, Any] | None = None,
) -> SceneRecord:
    """Tracks and frames of an opened scan (any reader of the ``Scan`` protocol), ``skips`` the
    reader's own. Inside a build, rows past the first row group are spilled to disk as encoded."""
    with frame_sink(scan.scene_id) as sink:
        grid = OutputGrid.for_scan(scan.calibration, options.size)
        tracked = track_scan(scan, masks.open_scan(scan), grid, options)
        tracked.skips.update(skips or Counter())
        if tracked.num_detections == 0:
            tracked.skips[SKIP_NO_DETECTIONS] += 1
        for row in scene_frames(scan, tracked, grid, options):
            sink.add(row)
        found = [Skip(reason, str(scan.path), count) for reason, count in sorted(tracked.skips.items()) if count]
        return sink.finish(skips=found, provenance=provenance)


def build_scene(unit: ScanUnit) -> SceneRecord:
    """The shared driver's per-unit function: one scan (top level: picklable)."""
    with open_scan(Path(unit.scene_dir), unit.scene_id) as scan:
        return convert_scan(scan, unit.masks, unit.options)
