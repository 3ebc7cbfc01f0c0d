"""Schema v1 folders: read transparently, validated, and migrated in place to the exact bytes of a v2 build."""

import json

import pytest

from usl.records import RecordsDataset
from usl.errors import UslError
from usl.records import migrate as migrate_module
from usl.cli.records import main as records_cli
from usl.records.migrate import migrate_dataset
from usl.records.validate import validate_dataset
from tests.records.v1_writer import write_v1_copy


def all_rows(root):
    out = {}
    for split in ("train", "val"):
        ds = RecordsDataset(root, split)
        out[split] = [(ds.read_scene(s), ds.read_objects(s)) for s in ds.scene_ids]
    return out


def shard_files(root):
    manifest = json.loads((root / "manifest.json").read_text())
    return [
        (s[t]["file"], s[t]["sha256"])
        for e in manifest["splits"].values()
        for s in e["shards"]
        for t in ("frames", "objects")
    ]


@pytest.fixture
def v1(fake_v2, tmp_path):
    return write_v1_copy(fake_v2, tmp_path / "v1")


def test_v1_reads_and_validates_like_v2(v1, fake_v2):
    assert all_rows(v1) == all_rows(fake_v2)
    assert validate_dataset(v1) == []
    assert records_cli(["info", str(v1), "--sheet", str(v1.parent / "sheet.png")]) == 0


def test_migrate_round_trip_gives_the_bytes_of_a_v2_build(v1, fake_v2, capsys):
    assert records_cli(["migrate", str(v1)]) == 0
    assert "6 shard file(s) rewritten" in capsys.readouterr().out  # frames + objects of 3 shards
    assert shard_files(v1) == shard_files(fake_v2)
    assert not (v1 / "train").exists() and not (v1 / "val").exists() and not (v1 / ".migrate.json").exists()
    assert (v1 / "README.md").read_text() == (fake_v2 / "README.md").read_text()
    assert validate_dataset(v1) == [] and all_rows(v1) == all_rows(fake_v2)
    assert migrate_dataset(v1).already_current


def test_crash_mid_migration_leaves_a_readable_dataset_and_a_rerun_finishes(v1, fake_v2, monkeypatch):
    real, calls = migrate_module._convert_file, []

    def dies_on_third(*args, **kwargs):
        calls.append(args)
        if len(calls) == 3:
            raise KeyboardInterrupt("killed")
        return real(*args, **kwargs)

    monkeypatch.setattr(migrate_module, "_convert_file", dies_on_third)
    with pytest.raises(KeyboardInterrupt):
        migrate_dataset(v1)
    assert json.loads((v1 / "manifest.json").read_text())["schema_version"] == 1
    assert validate_dataset(v1) == [] and all_rows(v1) == all_rows(fake_v2)
    monkeypatch.setattr(migrate_module, "_convert_file", real)
    summary = migrate_dataset(v1)
    assert (summary.reused, summary.files) == (2, 4)
    assert shard_files(v1) == shard_files(fake_v2) and validate_dataset(v1) == []


def test_crash_after_the_commit_point_reads_as_v2_and_a_rerun_cleans_up(v1, fake_v2, monkeypatch):
    def dies(*args):
        raise KeyboardInterrupt("killed")

    monkeypatch.setattr(migrate_module, "_remove_old", dies)
    with pytest.raises(KeyboardInterrupt):
        migrate_dataset(v1)
    assert (v1 / "train" / "frames-00000.parquet").exists() and validate_dataset(v1) == []
    assert all_rows(v1) == all_rows(fake_v2)
    monkeypatch.undo()
    summary = migrate_dataset(v1)
    assert summary.already_current and summary.removed == 6 and not (v1 / "train").exists()


def test_damaged_v1_shard_is_not_migrated(v1):
    shard = v1 / "val" / "frames-00000.parquet"
    shard.write_bytes(shard.read_bytes()[:-10])
    with pytest.raises(UslError, match="truncated"):
        migrate_dataset(v1)
    assert json.loads((v1 / "manifest.json").read_text())["schema_version"] == 1 and shard.exists()


def test_foreign_readme_is_kept(v1):
    (v1 / "README.md").write_text("my notes")
    with pytest.raises(UslError, match="not a usl dataset card"):
        migrate_dataset(v1)
    assert (v1 / "README.md").read_text() == "my notes"
