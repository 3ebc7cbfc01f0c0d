import pytest


@pytest.fixture(scope="session")
def fake_build(tmp_path_factory):
    """A small dataset in the current schema (train: 2 scenes in 2 shards, val: 1 scene) with 3D objects."""
    from pipelines.common import BuildOptions, ShardPlan, run_build
    from tests.records.fake_scenes import SPEC, build_fake_scene

    root = tmp_path_factory.mktemp("fake_build") / "ds"
    plans = [
        ShardPlan("train", 0, [("s0", 0, 3)]),
        ShardPlan("train", 1, [("s/1", 1, 4)]),
        ShardPlan("val", 0, [("s2", 2, 2)]),
    ]
    run_build(BuildOptions(root, progress=False), SPEC, {}, plans, build_fake_scene, {"command": "test"})
    return root
