"""The validator accepts a good dataset and names the file for each kind of damage."""

import json
import shutil

import numpy as np
import pyarrow.parquet as pq
import pytest

from pipelines.common import BuildOptions, ShardPlan, run_build
from tests.records.fake_scenes import SPEC, build_fake_scene
from usl.cli.records import main as records_cli
from usl.errors import UslError
from usl.records import RecordsDataset, encode_depth
from usl.records.validate import validate_dataset


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("valid") / "ds"
    plans = [ShardPlan("train", 0, [("s0", 0, 3), ("s1", 1, 4)]), ShardPlan("val", 0, [("s2", 2, 2)])]
    run_build(BuildOptions(root, progress=False), SPEC, {}, plans, build_fake_scene, {"command": "test"})
    return root


def copy(dataset, tmp_path):
    target = tmp_path / "copy"
    shutil.copytree(dataset, target)
    return target


def test_valid_dataset_passes(dataset, capsys):
    assert validate_dataset(dataset) == []
    assert records_cli(["validate", str(dataset)]) == 0
    assert records_cli(["info", str(dataset), "--sheet", str(dataset.parent / "sheet.png")]) == 0
    assert (dataset.parent / "sheet.png").stat().st_size > 0


def test_truncated_shard_is_rejected(dataset, tmp_path):
    root = copy(dataset, tmp_path)
    shard = root / "frames" / "train" / "frames-00000.parquet"
    shard.write_bytes(shard.read_bytes()[:-100])
    problems = validate_dataset(root)
    assert len(problems) == 1 and str(shard) in problems[0] and "truncated" in problems[0]


def test_wrong_checksum_is_rejected(dataset, tmp_path):
    root = copy(dataset, tmp_path)
    manifest = json.loads((root / "manifest.json").read_text())
    manifest["splits"]["val"]["shards"][0]["frames"]["sha256"] = "0" * 64
    (root / "manifest.json").write_text(json.dumps(manifest))
    problems = validate_dataset(root)
    assert len(problems) == 1 and "frames/val/frames-00000.parquet" in problems[0] and "sha256" in problems[0]


def test_unknown_schema_version_is_refused(dataset, tmp_path):
    root = copy(dataset, tmp_path)
    manifest = json.loads((root / "manifest.json").read_text())
    manifest["schema_version"] = 99
    (root / "manifest.json").write_text(json.dumps(manifest))
    assert "schema version 99 is not known" in validate_dataset(root)[0]
    with pytest.raises(UslError, match="schema version 99"):
        RecordsDataset(root, "train")


def test_shard_with_unknown_schema_version_is_refused(dataset, tmp_path):
    root = copy(dataset, tmp_path)
    path = root / "frames" / "val" / "frames-00000.parquet"
    table = pq.read_table(path)
    meta = json.loads(table.schema.metadata[b"usl"])
    meta["schema_version"] = 7
    pq.write_table(table.replace_schema_metadata({b"usl": json.dumps(meta).encode()}), path)
    manifest = json.loads((root / "manifest.json").read_text())
    info = manifest["splits"]["val"]["shards"][0]["frames"]
    from usl.records.shards import sha256_file

    info.update(bytes=path.stat().st_size, sha256=sha256_file(path))
    (root / "manifest.json").write_text(json.dumps(manifest))
    problems = validate_dataset(root)
    assert any(str(path) in p and "schema version 7" in p for p in problems)


def test_bad_content_is_named(dataset, tmp_path):
    root = copy(dataset, tmp_path)
    path = root / "frames" / "train" / "frames-00000.parquet"
    rows = pq.read_table(path).to_pylist()
    rows[1]["instances"][0]["box_xyxy"] = [-3.0, 0.0, 10.0, 10.0]
    rows[2]["cam_to_world"][0] = 2.0
    rows[3]["instances"][1]["category_id"] = 1
    rows[4]["depth"]["bytes"] = rows[4]["image"]["bytes"]  # an 8-bit colour PNG is no depth map
    rows[6]["depth"]["bytes"] = encode_depth(np.ones((8, 8)))
    table = pq.read_table(path)
    pq.write_table(type(table).from_pylist(rows, schema=table.schema), path)
    manifest = json.loads((root / "manifest.json").read_text())
    from usl.records.shards import sha256_file

    manifest["splits"]["train"]["shards"][0]["frames"].update(bytes=path.stat().st_size, sha256=sha256_file(path))
    (root / "manifest.json").write_text(json.dumps(manifest))
    problems = "\n".join(validate_dataset(root))
    assert "scene 's0' view 1: instance 7: box_xyxy" in problems
    assert "scene 's0' view 2: cam_to_world rotation is not orthonormal" in problems
    assert "scene 's1' view 1: instance 9 is category 2 here but 1 in another view" in problems
    assert "scene 's1' view 1: depth bytes are not a 16-bit PNG" in problems
    assert "scene 's1' view 3: depth is 8x8, row says 32x32" in problems
    assert "scene 's1' view 2: depth" not in problems  # no depth in that view (fake_scenes): nothing to check
