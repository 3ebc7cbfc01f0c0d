"""Shared machinery of the offline pipelines: the resumable, parallel, atomic build driver."""

from .driver import (
    BuildOptions,
    BuildSummary,
    ShardPlan,
    add_build_arguments,
    build_common_options,
    build_options_from_args,
    creator_from_args,
    fingerprint_from_args,
    run_build,
    scratch_dir,
)
from .spill import frame_sink

__all__ = [
    "BuildOptions",
    "BuildSummary",
    "ShardPlan",
    "add_build_arguments",
    "build_common_options",
    "build_options_from_args",
    "creator_from_args",
    "fingerprint_from_args",
    "frame_sink",
    "run_build",
    "scratch_dir",
]
