"""Long scenes streamed through spill files: same shards as in memory, resumable, flat memory."""

import json
import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from pipelines.common import BuildOptions, ShardPlan, run_build
from tests.records.fake_scenes import SPEC, build_fake_scene, build_streamed_fake_scene, fake_frames
from usl.records import RecordsDataset, SceneRecord
from usl.records.manifest import dataset_metadata
from usl.records.schema import table_schema
from usl.records.shards import MAX_ROWS_PER_GROUP, FrameSink, ShardWriter, frames_table

REPO = Path(__file__).parents[2]  # children import tests.records.* from the repository root
# Scene lengths around the row-group size (64), long ones spanning several groups, and an empty scene.
LENGTHS = [3, 150, 5, 64, 2, 0, 70, 100, 1, 1, 130, 65, 2, 4]


def plans(per_shard=4):
    units = [(f"scene{i:03d}", i, n) for i, n in enumerate(LENGTHS)]
    return [
        ShardPlan("train", k, units[start : start + per_shard])
        for k, start in enumerate(range(0, len(units), per_shard))
    ]


def build(out, build_scene, workers=1):
    return run_build(
        BuildOptions(out, workers=workers, progress=False), SPEC, {"v": 1}, plans(), build_scene, {"command": "test"}
    )


def shards(root):
    """Shard checksums plus the scene index: everything a reader relies on."""
    manifest = json.loads((root / "manifest.json").read_text())
    return [
        (s["frames"]["sha256"], (s["objects"] or {}).get("sha256"), s["scenes"])
        for e in manifest["splits"].values()
        for s in e["shards"]
    ]


@pytest.fixture(scope="module")
def in_memory(tmp_path_factory):
    root = tmp_path_factory.mktemp("memory") / "ds"
    build(root, build_fake_scene)
    return root


@pytest.mark.parametrize("workers", [1, 2])
def test_streamed_scenes_give_the_same_shards_as_in_memory(in_memory, tmp_path, workers):
    root = tmp_path / "streamed"
    summary = build(root, build_streamed_fake_scene, workers)
    assert summary.frames == sum(LENGTHS)
    assert shards(root) == shards(in_memory)
    assert not (root / ".build" / "spill").exists(), "spills are consumed and their folder removed"
    rows = RecordsDataset(root, "train").read_scene("scene010")
    assert [r["view_id"] for r in rows] == list(range(130))
    assert [r["image"] for r in rows] == [f["image"] for f in fake_frames("scene010", 10, 130)]
    groups = pq.ParquetFile(root / "frames" / "train" / "frames-00000.parquet").metadata
    # Scenes of 3, 150, 5, 64 rows: 3 + 150 fill two groups and the batch ends with the 150-row scene;
    # 5 + 64 then fill one more and end the next batch.
    assert [groups.row_group(i).num_rows for i in range(groups.num_row_groups)] == [64, 64, 25, 64, 5]


def test_sink_spills_only_past_one_row_group(tmp_path):
    with FrameSink("a/b", tmp_path) as sink:  # ids may hold "/": the spill name must stay in the folder
        for row in fake_frames("a/b", 0, MAX_ROWS_PER_GROUP):
            sink.add(row)
        short = sink.finish()
    assert len(short.frames) == MAX_ROWS_PER_GROUP and short.frames_file is None and not list(tmp_path.iterdir())
    with FrameSink("a/b", tmp_path) as sink:
        for row in fake_frames("a/b", 0, 150):
            sink.add(row)
        long = sink.finish()
    assert long.frames == [] and list(tmp_path.iterdir()) == [long.frames_file]
    spill = pq.ParquetFile(long.frames_file).metadata
    assert [spill.row_group(i).num_rows for i in range(spill.num_row_groups)] == [64, 64, 22]
    with pytest.raises(RuntimeError):
        with FrameSink("c", tmp_path) as sink:
            for row in fake_frames("c", 0, 100):
                sink.add(row)
            raise RuntimeError("pipeline failed mid-scene")
    assert list(tmp_path.iterdir()) == [long.frames_file], "a failed scene leaves no spill behind"


def test_rows_out_of_order_are_refused_by_the_sink_and_the_writer(tmp_path):
    rows = list(fake_frames("s", 1, 3))
    with pytest.raises(ValueError, match="ascending view_id"):
        with FrameSink("s", tmp_path) as sink:
            sink.add(rows[1])
            sink.add(rows[0])
    with pytest.raises(ValueError, match="another scene_id"):
        FrameSink("t", tmp_path).add(rows[0])
    swapped = [rows[0], rows[2], rows[1]]
    spill = tmp_path / "hand-made.parquet"
    pq.write_table(frames_table(swapped, table_schema("frames")), spill)
    for record in (SceneRecord("s", swapped), SceneRecord("s", [], frames_file=spill)):
        with pytest.raises(ValueError, match=r"ascending view_id \(1 after 2\)"):
            with ShardWriter(tmp_path / "ds", "train", 0, dataset_metadata(SPEC)) as writer:
                writer.add_scene(record)
        assert not list((tmp_path / "ds" / "frames" / "train").iterdir()), "a failed shard leaves no file"


KILLER = """
import os
from pathlib import Path
from tests.records import fake_scenes
from pipelines.common import frame_sink
from tests.records.test_streaming import build

def dying(unit):
    if unit[0] != "scene007":
        return fake_scenes.build_streamed_fake_scene(unit)
    with frame_sink(unit[0]) as sink:
        for row in fake_scenes.fake_frames(*unit):
            sink.add(row)
            if row["view_id"] == 80:  # one row group spilled, the rest in memory
                os._exit(3)

build(Path({out!r}), dying)
"""


def test_killed_build_with_a_half_written_spill_resumes_to_the_same_shards(in_memory, tmp_path):
    out = tmp_path / "interrupted"
    proc = subprocess.run([sys.executable, "-c", KILLER.format(out=str(out))], cwd=REPO)
    assert proc.returncode == 3
    assert list((out / ".build" / "spill").glob("*.parquet.tmp-*")), "the kill should leave a partial spill"
    summary = build(out, build_streamed_fake_scene)
    assert summary.kept_shards == 1 and summary.built_shards == 3
    assert not (out / ".build" / "spill").exists()
    assert shards(out) == shards(in_memory)


PEAK = """
import tracemalloc
from pathlib import Path
import numpy as np
import pyarrow as pa
from tests.records.fake_scenes import SPEC
from pipelines.common import BuildOptions, ShardPlan, frame_sink, run_build
from usl.records import SceneRecord, frame_row

STREAMED = {streamed}

def big_scene(unit):
    scene_id, views = unit
    rng = np.random.default_rng(views)
    rows = (frame_row(scene_id, v, rng.bytes(256 << 10), np.eye(3), np.eye(4), [], 64, 64) for v in range(views))
    if not STREAMED:
        return SceneRecord(scene_id, list(rows))
    with frame_sink(scene_id) as sink:
        for row in rows:
            sink.add(row)
        return sink.finish()

tracemalloc.start()
peaks = []
for views in (100, 400):
    tracemalloc.reset_peak()
    run_build(BuildOptions(Path({out!r}) / str(views), progress=False), SPEC, {{}},
              [ShardPlan("train", 0, [("long", views)])], big_scene, {{}})
    peaks.append(tracemalloc.get_traced_memory()[1] + pa.default_memory_pool().max_memory())
print((peaks[1] - peaks[0]) / 2**20)
"""


def test_peak_memory_stays_flat_in_scene_length_when_streamed(tmp_path):
    """A 100- then a 400-view scene of 256 KiB rows (75 MiB more data) built in one process (one worker:
    worker and writer share it). Peak = Python heap (tracemalloc) + Arrow pool, which, unlike RSS,
    allocator caching does not blur."""

    def growth_mib(streamed: bool) -> float:
        script = PEAK.format(out=str(tmp_path / str(streamed)), streamed=streamed)
        return float(
            subprocess.run(
                [sys.executable, "-c", script], cwd=REPO, check=True, capture_output=True, text=True
            ).stdout.split()[-1]
        )

    assert growth_mib(streamed=False) > 100  # the control: rows held in memory, then as Arrow, grow with the scene
    assert growth_mib(streamed=True) < 4
