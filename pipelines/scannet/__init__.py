"""ScanNet -> usl records: video frames with 2D instance masks tracked into objects (paper Sec. 4.3).

Entry point: ``usl-convert-scannet`` (``pipelines.scannet.cli:main``). Formats, options and what a
view sampler reads back: pipelines/scannet/README.md. The names below load on first use: the
converter imports torch, and ``usl-convert-scannet --help`` must not.
"""

from importlib import import_module

_EXPORTS = {
    "Calibration": "scan",
    "ConvertOptions": "convert",
    "DepthWarp": "warp",
    "Detection": "masks",
    "DetectionsFileSource": "detections_file",
    "ExportedScan": "exported",
    "FrameView": "masks",
    "IouTracker": "tracker",
    "MaskSource": "masks",
    "OutputGrid": "grid",
    "ScanMasks": "masks",
    "ScanNetLabelsSource": "scannet_labels",
    "ScanUnit": "convert",
    "SensScan": "sens",
    "SourceIdTracker": "tracker",
    "Track": "tracker",
    "TrackedScan": "convert",
    "TrackerConfig": "tracker",
    "TrackingQuality": "quality",
    "build_scene": "convert",
    "checked_rle": "masks",
    "open_scan": "convert",
    "split_detections": "detections_file",
    "track_scan": "convert",
    "tracking_quality": "quality",
}
__all__ = sorted(_EXPORTS)


def __getattr__(name: str):
    if name in _EXPORTS:
        return getattr(import_module(f".{_EXPORTS[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
