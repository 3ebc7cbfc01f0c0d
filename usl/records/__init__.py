"""Sharded Parquet multi-view records (docs/design.md §3): schema, encoding, writing, reading (v1, v2 and v3),
validation, migration and COCO export.

The reader (a torch ``IterableDataset``) is imported on first use, so tools that only write or
check records, and every ``--help``, start without loading torch.
"""

from .encode import (
    SceneRecord,
    Skip,
    decode_depth,
    decode_image,
    decode_mask,
    decoding,
    encode_depth,
    encode_image,
    encode_mask,
    frame_K,
    frame_pose,
    frame_row,
    image_bytes,
    make_instance,
    mask_bbox,
    object_mesh,
    object_row,
)
from .manifest import load_manifest
from .schema import SCHEMA_VERSION
from .shards import ShardResult, ShardWriter

__all__ = [
    "SCHEMA_VERSION",
    "RecordsDataset",
    "SceneRecord",
    "SceneStream",
    "ShardResult",
    "ShardWriter",
    "Skip",
    "decode_depth",
    "decode_image",
    "decode_mask",
    "decoding",
    "encode_depth",
    "encode_image",
    "encode_mask",
    "frame_K",
    "frame_pose",
    "frame_row",
    "image_bytes",
    "load_manifest",
    "make_instance",
    "mask_bbox",
    "object_mesh",
    "object_row",
    "partition",
]

_LAZY = {"RecordsDataset": "reader", "SceneStream": "reader", "partition": "reader"}


def __getattr__(name: str):
    if name in _LAZY:
        from importlib import import_module

        return getattr(import_module(f".{_LAZY[name]}", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
