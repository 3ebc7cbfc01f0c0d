"""Writer/driver/reader round trip: resume after a killed build, worker/rank partition, errors."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from torch.utils.data import DataLoader

from pipelines.common import BuildOptions, ShardPlan, run_build
from tests.records.fake_scenes import SPEC, build_fake_scene
from tests.records.old_writer import write_old_file
from usl.data.loader import worker_start_method
from usl.errors import UslError
from usl.records import RecordsDataset, SceneStream, decode_mask
from usl.records.schema import file_schema_version

REPO = Path(__file__).parents[2]  # children import tests.records.* from the repository root


def make_plans(num_scenes=10, per_shard=3):
    units = [(f"scene{i:03d}", i, 2 + i % 4) for i in range(num_scenes)]
    return [
        ShardPlan("train", k, units[k * per_shard : (k + 1) * per_shard])
        for k in range((num_scenes + per_shard - 1) // per_shard)
    ]


def build(out, workers=1, plans=None):
    return run_build(
        BuildOptions(out, workers=workers, progress=False),
        SPEC,
        {"v": 1},
        plans or make_plans(),
        build_fake_scene,
        {"command": "test"},
    )


def checksums(root):
    manifest = json.loads((root / "manifest.json").read_text())
    return {
        s["frames"]["file"]: (s["frames"]["sha256"], (s["objects"] or {}).get("sha256"))
        for e in manifest["splits"].values()
        for s in e["shards"]
    }


KILLER = """
import os
from pathlib import Path
from tests.records import fake_scenes
from pipelines.common import BuildOptions, run_build
from tests.records.test_build_and_read import make_plans

def dying(unit):
    if unit[0] == "scene007":
        os._exit(3)  # simulate a kill in the middle of the third shard
    return fake_scenes.build_fake_scene(unit)

run_build(BuildOptions(Path({out!r}), progress=False), fake_scenes.SPEC, {{"v": 1}}, make_plans(), dying, {{"command": "test"}})
"""


def test_resume_after_kill_matches_uninterrupted_build(tmp_path):
    reference = tmp_path / "reference"
    build(reference)
    interrupted = tmp_path / "interrupted"
    proc = subprocess.run([sys.executable, "-c", KILLER.format(out=str(interrupted))], cwd=REPO)
    assert proc.returncode == 3
    assert not (interrupted / "manifest.json").exists()
    assert list(interrupted.glob("frames/train/*.tmp-*")), (
        "the killed build should leave its partial shard as a temp file"
    )
    summary = build(interrupted)
    assert summary.kept_shards == 2 and summary.built_shards == 2
    assert not list(interrupted.glob("frames/train/*.tmp-*"))
    assert checksums(interrupted) == checksums(reference)


def test_round_trip_and_worker_count_determinism(tmp_path):
    one, two = tmp_path / "one", tmp_path / "two"
    build(one, workers=1)
    build(two, workers=2)
    assert checksums(one) == checksums(two)
    ds = RecordsDataset(one, "train")
    assert ds.scene_ids == [f"scene{i:03d}" for i in range(10)]
    expected = build_fake_scene(("scene005", 5, 3))
    rows = ds.read_scene("scene005")
    assert [r["view_id"] for r in rows] == [0, 1, 2]
    for got, want in zip(rows, expected.frames, strict=True):
        assert got["image"] == want["image"] and got["K"] == want["K"]
        for g, w in zip(got["instances"], want["instances"], strict=True):
            np.testing.assert_array_equal(decode_mask(g["mask"]), decode_mask(w["mask"]))
            assert g["box_xyxy"] == w["box_xyxy"] and g["instance_id"] == w["instance_id"]
    assert [r["view_id"] for r in ds.read_scene("scene005", views=[2, 0])] == [2, 0]
    objects = ds.read_objects("scene005")
    np.testing.assert_allclose(np.asarray(objects[1]["vertices"]), np.asarray(expected.objects[1]["vertices"]))


def test_no_duplicates_or_losses_across_workers_and_ranks(tmp_path):
    build(tmp_path / "ds")
    ds = RecordsDataset(tmp_path / "ds", "train")
    seen = []
    for rank in range(2):
        stream = SceneStream(ds, rank=rank, world_size=2, shuffle=True, seed=3, columns=["scene_id", "view_id"])
        # workers start as training's do: never by fork (the stream travels to them pickled)
        loader = DataLoader(stream, batch_size=None, num_workers=2, multiprocessing_context=worker_start_method())
        seen += [scene_id for scene_id, rows in loader if all(r["scene_id"] == scene_id for r in rows)]
    assert sorted(seen) == sorted(ds.scene_ids)


def test_skips_are_recorded_and_foreign_folder_refused(tmp_path):
    plans = [ShardPlan("val", 0, [("a", 1, 2), ("empty", 2, 0)])]
    build(tmp_path / "ds", plans=plans)
    manifest = json.loads((tmp_path / "ds" / "manifest.json").read_text())
    assert manifest["num_skipped"] == 1 and manifest["skips"][0]["path"] == "empty.fake"
    with pytest.raises(UslError, match="other arguments"):
        run_build(BuildOptions(tmp_path / "ds", progress=False), SPEC, {"v": 2}, plans, build_fake_scene, {})
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(UslError, match="not empty"):
        build(tmp_path / "other", plans=plans)


def test_split_build_across_machines_then_finalise(tmp_path):
    out = tmp_path / "ds"
    for index in range(2):
        summary = run_build(
            BuildOptions(out, num_shards=2, shard_index=index, progress=False),
            SPEC,
            {"v": 1},
            make_plans(),
            build_fake_scene,
            {},
        )
    assert summary.manifest_written and summary.kept_shards == 2 and summary.built_shards == 2
    assert len(RecordsDataset(out, "train")) == 10


def test_finished_shard_in_an_older_layout_is_rebuilt_not_mixed_in(tmp_path):
    """A build begun by usl 0.1 (v1 layout) and resumed now: its finished shards are redone in v2."""
    out = tmp_path / "ds"
    plans = make_plans(num_scenes=4, per_shard=2)
    build(out, plans=plans)
    marker = out / ".build" / "train-00000.json"
    result = json.loads(marker.read_text())
    (out / "train").mkdir()
    (out / "frames" / "train" / "frames-00000.parquet").rename(out / "train" / "frames-00000.parquet")
    result["frames"]["file"] = "train/frames-00000.parquet"
    marker.write_text(json.dumps(result))
    summary = build(out, plans=plans)
    assert (summary.kept_shards, summary.built_shards) == (1, 1)
    assert json.loads((out / "manifest.json").read_text())["splits"]["train"]["shards"][0]["frames"]["file"] == (
        "frames/train/frames-00000.parquet"
    )


def test_finished_shard_of_an_older_schema_is_rebuilt_not_mixed_in(tmp_path):
    """A build begun by a usl that wrote v2 (same paths) and resumed now: its v2 shard is redone in v3."""
    out = tmp_path / "ds"
    plans = make_plans(num_scenes=4, per_shard=2)
    build(out, plans=plans)
    before = checksums(out)
    marker = out / ".build" / "train-00000.json"
    result = json.loads(marker.read_text())
    frames = out / result["frames"]["file"]
    result["frames"].update(write_old_file(frames, frames.with_name("v2.parquet"), "frames", 2))
    frames.with_name("v2.parquet").replace(frames)
    marker.write_text(json.dumps(result))
    summary = build(out, plans=plans)
    assert (summary.kept_shards, summary.built_shards) == (1, 1)
    assert checksums(out) == before and file_schema_version(frames) == 3
