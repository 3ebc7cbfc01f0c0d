"""From records to tensors: decoded frames, multi-view samples and batches."""
from .dataset import MultiViewDataset, SampleKey, decode_target_view, input_target_view
from .frames import CategoryIndex, FrameData, decode_frame
from .loader import ShardedBatchSampler, build_train_loader
from .samples import MultiViewSample, TargetView, collate_samples
from .sampling import sample_other_views
from .transforms import resize_frame, resize_target_view, resized_shape

__all__ = [
    "CategoryIndex",
    "FrameData",
    "MultiViewDataset",
    "MultiViewSample",
    "SampleKey",
    "ShardedBatchSampler",
    "TargetView",
    "build_train_loader",
    "collate_samples",
    "decode_frame",
    "decode_target_view",
    "input_target_view",
    "resize_frame",
    "resize_target_view",
    "resized_shape",
    "sample_other_views",
]
