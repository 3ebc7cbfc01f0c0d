"""Sharded Parquet multi-view records (DESIGN.md §3): schema, encoding, writing, reading (v1 and v2),
validation, migration and COCO export."""
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
from .errors import UslError
from .manifest import load_manifest
from .reader import RecordsDataset, SceneStream, partition
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
    "UslError",
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
