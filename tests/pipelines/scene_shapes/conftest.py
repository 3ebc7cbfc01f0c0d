"""A tiny Scene-Shapes dataset built once per test run through the real CLI."""

from pathlib import Path

import pytest

from pipelines.scene_shapes.cli import main

TINY = [
    "--num-scenes",
    "10",
    "--num-models",
    "30",
    "--resolution",
    "96",
    "--azimuths",
    "3",
    "--heights",
    "2",
    "--scenes-per-shard",
    "4",
    "--seed",
    "5",
    "--quiet",
]


@pytest.fixture(scope="session")
def tiny_dataset(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("scene_shapes") / "tiny"
    assert main(["--out", str(out), *TINY]) == 0
    return out
