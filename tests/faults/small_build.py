"""The small Scene-Shapes build the fault tests break: three scenes, one per shard (train, val, test)."""

from __future__ import annotations

from pathlib import Path

from pipelines.scene_shapes.cli import main

ARGS = "--num-scenes 3 --num-models 12 --resolution 16 --views 2 --heights 1 --scenes-per-shard 1 --quiet".split()


def build(out: Path, *extra: str, seed: int = 3) -> int:
    """``usl-build-scene-shapes`` in this process; its exit status."""
    return main(["--out", str(out), *ARGS, "--seed", str(seed), *extra])
