"""From records to tensors: decoded frames, multi-view samples and batches."""
from .frames import CategoryIndex, FrameData, decode_frame

__all__ = ["CategoryIndex", "FrameData", "decode_frame"]
