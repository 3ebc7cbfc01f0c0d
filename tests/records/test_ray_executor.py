"""``--executor ray`` runs the same shard plan as Ray tasks and writes the same bytes as local."""

import pytest

from pipelines.common import BuildOptions, ShardPlan, run_build
from tests.records.fake_scenes import SPEC, build_fake_scene, build_streamed_fake_scene

pytest.importorskip("ray")


def plans():
    # Scene lengths around the row-group size, a long one that a local worker would spill, an empty one.
    units = [(f"scene{i:03d}", i, n) for i, n in enumerate([3, 150, 5, 0, 70, 2, 1])]
    return [ShardPlan("train", 0, units[:3]), ShardPlan("train", 1, units[3:5]), ShardPlan("val", 0, units[5:])]


def build(out, build_scene, **options):
    return run_build(BuildOptions(out, progress=False, **options), SPEC, {"v": 1}, plans(), build_scene, {})


def shard_bytes(root):
    return {p.relative_to(root): p.read_bytes() for p in sorted(root.rglob("*.parquet")) if ".build" not in p.parts}


def test_ray_executor_writes_the_same_bytes_as_local(local_ray, tmp_path):
    build(tmp_path / "local", build_streamed_fake_scene, workers=2)
    summary = build(tmp_path / "ray", build_streamed_fake_scene, executor="ray")
    assert summary.manifest_written and summary.built_shards == 3
    local, remote = shard_bytes(tmp_path / "local"), shard_bytes(tmp_path / "ray")
    assert len(local) == 6 and local == remote
    # Resuming a Ray build locally (or the other way round) keeps its shards: same build, other executor.
    assert build(tmp_path / "ray", build_fake_scene).kept_shards == 3
