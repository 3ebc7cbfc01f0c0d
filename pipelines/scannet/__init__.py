"""ScanNet -> usl records: video frames with 2D instance masks tracked into objects (paper Sec. 4.3).

Entry point: ``usl-convert-scannet`` (``pipelines.scannet.cli:main``). Formats, options and what a
view sampler reads back: pipelines/scannet/README.md.
"""
from .convert import ConvertOptions, ScanUnit, TrackedScan, build_scene, track_scan
from .detections_file import DetectionsFileSource, split_detections
from .exported import ExportedScan
from .grid import OutputGrid
from .masks import Detection, FrameView, MaskSource, ScanMasks, checked_rle
from .quality import TrackingQuality, tracking_quality
from .scan import Calibration, open_scan
from .scannet_labels import ScanNetLabelsSource
from .sens import SensScan
from .tracker import IouTracker, SourceIdTracker, Track, TrackerConfig
from .warp import DepthWarp

__all__ = [
    "Calibration",
    "ConvertOptions",
    "DepthWarp",
    "Detection",
    "DetectionsFileSource",
    "ExportedScan",
    "FrameView",
    "IouTracker",
    "MaskSource",
    "OutputGrid",
    "ScanMasks",
    "ScanNetLabelsSource",
    "ScanUnit",
    "SensScan",
    "SourceIdTracker",
    "Track",
    "TrackedScan",
    "TrackerConfig",
    "TrackingQuality",
    "build_scene",
    "checked_rle",
    "open_scan",
    "split_detections",
    "track_scan",
    "tracking_quality",
]
