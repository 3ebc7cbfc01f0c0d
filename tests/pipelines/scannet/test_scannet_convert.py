"""End to end: ``usl-convert-scannet`` on a .sens scan and an exported scan, checked against the
synthetic truth, the record validator, and what a view sampler needs to read back."""

from __future__ import annotations

import dataclasses
import json
import pickle
import shutil
from collections import defaultdict

import numpy as np
import pyarrow.parquet as pq
import pytest

from pipelines.common.spill import set_spill_dir
from pipelines.scannet.cli import main
from pipelines.scannet.convert import SKIP_DEPTH, SKIP_POSE, ConvertOptions, ScanUnit, build_scene
from pipelines.scannet.scannet_labels import ScanNetLabelsSource
from tests.pipelines.scannet.synthetic_scan import SyntheticScan, write_label_map, write_labels, write_sens
from usl.records import RecordsDataset, decode_depth, decode_image, decode_mask, load_manifest
from usl.records.schema import file_schema_version
from usl.records.validate import validate_dataset

SENS_SCENE, EXPORTED_SCENE = "scene0001_00", "scene0002_00"


def convert(synthetic, out, *extra: str) -> int:
    args = [
        "--out",
        str(out),
        "--quiet",
        "--scans-root",
        str(synthetic.scans),
        "--splits-dir",
        str(synthetic.splits),
        "--stride",
        "1",
        "--resolution",
        "48x36",
    ]
    if "--masks" not in extra:  # later arguments win
        args += ["--detections", *map(str, synthetic.results), "--detection-images", str(synthetic.images)]
    return main(args + list(extra))


@pytest.fixture(scope="module")
def converted(synthetic, tmp_path_factory):
    out = tmp_path_factory.mktemp("records") / "scannet"
    assert convert(synthetic, out) == 0
    return out


def skips_of(root) -> dict[str, int]:
    counts: dict[str, int] = defaultdict(int)
    for skip in load_manifest(root)["skips"]:
        counts[skip["reason"]] += skip["count"]
    return dict(counts)


def track_frames(dataset: RecordsDataset, scene_id: str) -> dict[int, list[int]]:
    """What a view sampler does: instance id -> its frames (view ids, time order), from two columns."""
    frames: dict[int, list[int]] = defaultdict(list)
    for row in dataset.read_scene(scene_id, columns=["view_id", "instances"]):
        for inst in row["instances"]:
            frames[inst["instance_id"]].append(row["view_id"])
    return dict(frames)


def test_records_are_valid_and_complete(converted, synthetic):
    assert validate_dataset(converted) == []
    manifest = load_manifest(converted)
    assert (
        manifest["schema_version"] == 3
        and {file_schema_version(p) for p in (converted / "frames").rglob("*.parquet")} == {3}  # depth an Image
        and (converted / "frames" / "train").is_dir()
        and (converted / "README.md").exists()
    )
    assert set(manifest["splits"]) == {"train", "val"}
    assert skips_of(converted) == {SKIP_POSE: 2 * len(synthetic.lost)}
    train = RecordsDataset(converted, "train")
    rows = train.read_scene(SENS_SCENE)
    assert [r["view_id"] for r in rows] == [i for i in range(120) if i not in synthetic.lost]
    tracks = track_frames(train, SENS_SCENE)
    assert len(tracks) == 3 and all(len(v) >= 50 for v in tracks.values())  # the 23-frame chair is dropped
    assert all(v == sorted(v) for v in tracks.values())


def test_records_match_the_synthetic_truth(converted, synthetic):
    rows = RecordsDataset(converted, "train").read_scene(SENS_SCENE)
    scan = synthetic.scan
    K = np.asarray(rows[0]["K"]).reshape(3, 3)
    np.testing.assert_allclose(K, np.diag([0.5, 0.5, 1.0]) @ scan.K_color, atol=1e-4)  # 96x72 -> 48x36
    identity: dict[int, int] = {}  # record instance id -> synthetic box
    for row in rows[::9]:
        frame = synthetic.frames[row["view_id"]]
        assert decode_image(row["image"]).shape == (36, 48, 3)
        pose = np.asarray(row["cam_to_world"]).reshape(4, 4)
        np.testing.assert_allclose(pose, scan.true_pose(frame.index), atol=1e-6)
        depth = decode_depth(row["depth"])
        np.testing.assert_array_equal(np.nan_to_num(depth * 1000).round(), frame.depth_mm)  # 48x36 = depth camera
        truth = frame.instances[1::2, 1::2]  # nearest at pixel centres of a 2x downsampling
        for inst in row["instances"]:
            mask = decode_mask(inst["mask"])
            box = int(np.bincount(truth[mask]).argmax())
            assert identity.setdefault(inst["instance_id"], box) == box  # one box per instance id, always
            np.testing.assert_array_equal(mask, truth == box)
            assert inst["depth_min"] == pytest.approx(depth[mask].min())
    categories = {b.instance: b.coco_id for b in scan.boxes}
    assert sorted(categories[b] for b in identity.values()) == [62, 63, 72]


def test_exported_scan_gives_the_same_records(converted):
    a = RecordsDataset(converted, "train").read_scene(SENS_SCENE)
    b = RecordsDataset(converted, "val").read_scene(EXPORTED_SCENE)
    assert [r["view_id"] for r in a] == [r["view_id"] for r in b]
    for ra, rb in zip(a[::10], b[::10], strict=True):
        assert ra["image"] == rb["image"] and ra["depth"] == rb["depth"]
        np.testing.assert_allclose(ra["K"], rb["K"], rtol=1e-6)  # .sens stores float32
        np.testing.assert_allclose(ra["cam_to_world"], rb["cam_to_world"], atol=1e-6)
        assert [i["mask"] for i in ra["instances"]] == [i["mask"] for i in rb["instances"]]


def test_native_size_keeps_the_stored_jpeg_and_labels_give_ground_truth_tracks(synthetic, tmp_path):
    out = tmp_path / "native"
    assert (
        convert(
            synthetic,
            out,
            "--resolution",
            "native",
            "--splits",
            "train",
            "--masks",
            "scannet-labels",
            "--label-map",
            str(synthetic.labels),
            "--tracker",
            "source-ids",
        )
        == 0
    )
    assert validate_dataset(out) == []
    rows = RecordsDataset(out, "train").read_scene(SENS_SCENE)
    for row in rows[::20]:
        frame = synthetic.frames[row["view_id"]]
        assert row["image"]["bytes"] == frame.color and (row["height"], row["width"]) == (72, 96)
        for inst in row["instances"]:  # ScanNet's instance ids become the instance ids
            np.testing.assert_array_equal(decode_mask(inst["mask"]), frame.instances == inst["instance_id"])
    assert sorted(track_frames(RecordsDataset(out, "train"), SENS_SCENE)) == [1, 2, 3]


def test_rerun_keeps_finished_shards(converted, synthetic, capsys):
    assert convert(synthetic, converted) == 0
    assert "built 0 shard(s), kept 2" in capsys.readouterr().out


def test_empty_depth_frames_are_skipped_and_counted(tmp_path):
    scan = SyntheticScan(num_frames=60, color_size=(32, 24), depth_size=(16, 12))
    frames = list(scan.frames())
    frames[3] = dataclasses.replace(frames[3], depth_mm=np.zeros((12, 16), np.uint16))
    frames[4] = dataclasses.replace(frames[4], depth_mm=np.zeros((0, 0), np.uint16))  # no depth payload at all
    (tmp_path / "scene0003_00").mkdir()
    write_sens(tmp_path / "scene0003_00" / "scene0003_00.sens", scan, frames)
    write_labels(tmp_path / "scene0003_00", scan, frames)
    write_label_map(tmp_path / "labels.tsv")
    source = ScanNetLabelsSource(str(tmp_path / "labels.tsv"), ((1, "chair"), (2, "couch"), (7, "tv")))
    options = ConvertOptions(stride=1, size=None)
    unit = ScanUnit("scene0003_00", str(tmp_path / "scene0003_00"), source, options)
    unit = pickle.loads(pickle.dumps(unit))  # travels to spawned build workers
    record = build_scene(unit)
    skips = {s.reason: s.count for s in record.skips}
    assert skips[SKIP_DEPTH] == 2
    assert [f["view_id"] for f in record.frames][:4] == [0, 1, 2, 5]
    assert len(record.frames) + sum(skips.values()) == 60  # every frame is written or counted


def test_bad_input_fails_with_the_file_named(synthetic, tmp_path, capsys):
    assert convert(synthetic, tmp_path / "a", "--detection-images", str(tmp_path / "nope.json")) == 2
    assert "nope.json: no such file" in capsys.readouterr().err
    broken = tmp_path / "scans" / SENS_SCENE
    broken.mkdir(parents=True)
    data = synthetic.sens.read_bytes()
    (broken / f"{SENS_SCENE}.sens").write_bytes(data[: len(data) // 2])
    args = [
        "--out",
        str(tmp_path / "b"),
        "--quiet",
        "--scans-root",
        str(tmp_path / "scans"),
        "--splits-dir",
        str(synthetic.splits),
        "--splits",
        "train",
        "--masks",
        "scannet-labels",
        "--label-map",
        str(synthetic.labels),
    ]
    assert main(args) == 2
    assert f"{SENS_SCENE}.sens: truncated .sens file" in capsys.readouterr().err
    missing = [
        "--out",
        str(tmp_path / "c"),
        "--quiet",
        "--scans-root",
        str(tmp_path / "scans"),
        "--splits-dir",
        str(synthetic.splits),
        "--masks",
        "scannet-labels",
        "--label-map",
        str(synthetic.labels),
    ]
    assert main(missing) == 2
    assert "scan folder(s) missing, e.g. scene0002_00" in capsys.readouterr().err


def test_a_bad_scan_among_good_ones_is_a_recorded_skip_and_the_build_completes(synthetic, tmp_path, capsys):
    scans, splits = tmp_path / "scans", tmp_path / "splits"
    (scans / SENS_SCENE).mkdir(parents=True)
    data = synthetic.sens.read_bytes()
    (scans / SENS_SCENE / f"{SENS_SCENE}.sens").write_bytes(data[: len(data) // 2])
    shutil.copytree(synthetic.exported, scans / EXPORTED_SCENE)
    splits.mkdir()
    (splits / "scannetv2_train.txt").write_text(f"{SENS_SCENE}\n{EXPORTED_SCENE}\n")
    args = [
        "--out",
        str(tmp_path / "out"),
        "--quiet",
        "--scans-root",
        str(scans),
        "--splits-dir",
        str(splits),
        "--splits",
        "train",
        "--masks",
        "scannet-labels",
        "--label-map",
        str(synthetic.labels),
        "--stride",
        "2",
        "--resolution",
        "48x36",
    ]
    assert main(args + ["--no-skip-bad-scenes"]) == 2
    assert f"{SENS_SCENE}.sens: truncated .sens file" in capsys.readouterr().err
    assert main(args) == 0
    skips = [s for s in load_manifest(tmp_path / "out")["skips"] if s["reason"].startswith("scene not converted")]
    assert len(skips) == 1 and f"{SENS_SCENE}.sens: truncated .sens file" in skips[0]["reason"]
    assert skips[0]["path"] == str(scans / SENS_SCENE)
    assert RecordsDataset(tmp_path / "out", "train").scene_ids == [EXPORTED_SCENE]
    assert validate_dataset(tmp_path / "out") == []
    assert main(args) == 0 and "built 0 shard(s), kept 1" in capsys.readouterr().out


def test_manifest_records_the_tracking_arguments(converted):
    creator = load_manifest(converted)["creator"]
    assert creator["command"] == "usl-convert-scannet"
    assert creator["arguments"]["min_track_frames"] == 50 and json.dumps(creator)


def test_inside_a_build_a_scan_streams_its_rows_to_a_spill_file(synthetic, tmp_path):
    source = ScanNetLabelsSource(str(synthetic.labels), ((1, "chair"), (2, "couch"), (7, "tv")))
    unit = ScanUnit(SENS_SCENE, str(synthetic.sens.parent), source, ConvertOptions(stride=1, size=(48, 36)))
    in_memory = build_scene(unit)  # outside a build: rows in the record
    set_spill_dir(tmp_path)  # what run_build does in every worker
    try:
        streamed = build_scene(unit)
    finally:
        set_spill_dir(None)
    assert streamed.frames == [] and streamed.frames_file.parent == tmp_path
    assert streamed.skips == in_memory.skips
    spilled = pq.read_table(streamed.frames_file).to_pylist()
    assert len(spilled) == len(in_memory.frames) == 120 - len(synthetic.lost)
    for a, b in zip(spilled, in_memory.frames, strict=True):
        assert (a["view_id"], a["image"], a["depth"], a["K"]) == (b["view_id"], b["image"], b["depth"], b["K"])
        assert json.dumps(a["instances"]) == json.dumps(b["instances"])  # NaN depth_min compares equal as text
