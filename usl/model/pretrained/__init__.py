"""Start a detector from pretrained torchvision / detectron2 weights (``model.init_weights``)."""

from .files import FORMATS, WeightsError, WeightsFile, read_weights, resolve_format
from .layouts import CLASS_SPECIFIC, LAYOUTS, Layout
from .loader import InitReport, init_detector, print_report, trained_stride_in_1x1

__all__ = [
    "CLASS_SPECIFIC",
    "FORMATS",
    "InitReport",
    "LAYOUTS",
    "Layout",
    "WeightsError",
    "WeightsFile",
    "init_detector",
    "print_report",
    "read_weights",
    "resolve_format",
    "trained_stride_in_1x1",
]
