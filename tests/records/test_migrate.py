"""Schema v1 and v2 folders: read transparently, validated, and migrated in place to the exact bytes of a
current build."""

import json
import os
import socket
import subprocess
import sys

import pandas as pd
import pytest

from tests.records.old_writer import write_old_copy
from usl.cli.records import main as records_cli
from usl.errors import UslError
from usl.records import RecordsDataset
from usl.records import migrate as migrate_module
from usl.records.migrate import migrate_dataset
from usl.records.validate import validate_dataset


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


def visible_files(root):
    """Every file that tools skipping hidden names see, with its bytes."""
    files = (p for p in root.rglob("*") if p.is_file())
    return {p: p.read_bytes() for p in files if not any(part.startswith(".") for part in p.relative_to(root).parts)}


def schema_version(root):
    return json.loads((root / "manifest.json").read_text())["schema_version"]


@pytest.fixture
def v1(fake_build, tmp_path):
    return write_old_copy(fake_build, tmp_path / "v1", 1)


@pytest.fixture(params=[1, 2], ids=["v1", "v2"])
def old(request, fake_build, tmp_path):
    return write_old_copy(fake_build, tmp_path / f"v{request.param}", request.param)


def test_old_versions_read_and_validate_like_the_current_build(old, fake_build):
    assert all_rows(old) == all_rows(fake_build)
    assert validate_dataset(old) == []
    assert records_cli(["info", str(old), "--sheet", str(old.parent / "sheet.png")]) == 0


def test_migrate_round_trip_gives_the_bytes_of_a_current_build(old, fake_build, capsys):
    version = schema_version(old)
    assert records_cli(["migrate", str(old)]) == 0
    out = capsys.readouterr().out
    assert f"from schema v{version} to v3: 6 shard file(s) rewritten" in out  # frames + objects of 3 shards
    assert shard_files(old) == shard_files(fake_build)
    assert not (old / "train").exists() and not (old / "val").exists() and not (old / ".migrate.json").exists()
    assert not [p for p in old.rglob(".*") if p.name != ".lock"]  # no staged or temp file left
    assert (old / "README.md").read_text() == (fake_build / "README.md").read_text()
    assert validate_dataset(old) == [] and all_rows(old) == all_rows(fake_build)
    assert migrate_dataset(old).already_current


def test_crash_mid_migration_leaves_the_old_dataset_readable_and_a_rerun_finishes(old, fake_build, monkeypatch):
    version, before = schema_version(old), visible_files(old)
    real, calls = migrate_module._convert_file, []

    def dies_on_third(*args, **kwargs):
        calls.append(args)
        if len(calls) == 3:
            raise KeyboardInterrupt("killed")
        return real(*args, **kwargs)

    monkeypatch.setattr(migrate_module, "_convert_file", dies_on_third)
    with pytest.raises(KeyboardInterrupt):
        migrate_dataset(old)
    assert schema_version(old) == version
    assert validate_dataset(old) == [] and all_rows(old) == all_rows(fake_build)
    # the converted shards wait hidden: pandas, pyarrow.dataset and Hugging Face see the old folder as it was
    assert visible_files(old) == before
    if version == 2:
        assert len(pd.read_parquet(old / "frames" / "train")) == 7
    monkeypatch.setattr(migrate_module, "_convert_file", real)
    summary = migrate_dataset(old)
    assert (summary.reused, summary.files) == (2, 4)
    assert shard_files(old) == shard_files(fake_build) and validate_dataset(old) == []


def test_crash_while_renaming_v2_shards_is_finished_by_a_rerun(fake_build, tmp_path, monkeypatch):
    """From v2 the converted shards take the v2 paths: a crash between two renames leaves a folder
    that a rerun completes without converting anything again."""
    v2 = write_old_copy(fake_build, tmp_path / "v2", 2)
    real, calls = os.replace, []

    def dies_on_second_rename(src, dst):
        if str(src).endswith(".v3"):
            calls.append(dst)
            if len(calls) == 2:
                raise KeyboardInterrupt("killed")
        return real(src, dst)

    monkeypatch.setattr(migrate_module.os, "replace", dies_on_second_rename)
    with pytest.raises(KeyboardInterrupt):
        migrate_dataset(v2)
    assert schema_version(v2) == 2
    monkeypatch.undo()
    with pytest.raises(UslError, match="truncated or replaced"):  # the renamed shard is not the v2 one
        RecordsDataset(v2, "train").read_scene("s0")
    summary = migrate_dataset(v2)
    assert (summary.reused, summary.files, summary.removed) == (6, 0, 0)
    assert shard_files(v2) == shard_files(fake_build) and validate_dataset(v2) == []
    assert all_rows(v2) == all_rows(fake_build)


def test_crash_after_the_commit_point_reads_as_current_and_a_rerun_cleans_up(v1, fake_build, monkeypatch):
    def dies(*args):
        raise KeyboardInterrupt("killed")

    monkeypatch.setattr(migrate_module, "_remove_old", dies)
    with pytest.raises(KeyboardInterrupt):
        migrate_dataset(v1)
    assert (v1 / "train" / "frames-00000.parquet").exists() and validate_dataset(v1) == []
    assert all_rows(v1) == all_rows(fake_build)
    monkeypatch.undo()
    summary = migrate_dataset(v1)
    assert summary.already_current and summary.removed == 6 and not (v1 / "train").exists()


def test_damaged_old_shard_is_not_migrated(old):
    version = schema_version(old)
    shard = old / ("frames/val/frames-00000.parquet" if version == 2 else "val/frames-00000.parquet")
    damaged = shard.read_bytes()[:-10]
    shard.write_bytes(damaged)
    with pytest.raises(UslError, match=f"{shard}: size .* \\(truncated or replaced\\)"):
        migrate_dataset(old)
    assert schema_version(old) == version and shard.read_bytes() == damaged


def test_foreign_readme_is_kept(v1):
    (v1 / "README.md").write_text("my notes")
    with pytest.raises(UslError, match="not a usl dataset card"):
        migrate_dataset(v1)
    assert (v1 / "README.md").read_text() == "my notes"


HOLD_FOLDER = """
import sys
from pathlib import Path
from usl.records.claims import sole_writer
with sole_writer(Path(sys.argv[1]), "usl-records migrate"):
    print("held", flush=True)
    sys.stdin.read()
"""


def test_a_second_migration_is_refused_in_one_line_and_a_dead_ones_lock_is_taken_over(v1, capsys):
    holder = subprocess.Popen(
        [sys.executable, "-c", HOLD_FOLDER, str(v1)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True
    )
    try:
        assert holder.stdout.readline() == "held\n"
        before = {p: p.read_bytes() for p in v1.rglob("*") if p.is_file() and ".lock" not in p.parts}
        assert records_cli(["migrate", str(v1)]) == 2
        error = capsys.readouterr().err.strip()
        assert error.count("\n") == 0 and "usl-records migrate is already writing here" in error
        assert f"pid {holder.pid} on {socket.gethostname()}" in error
        assert {p: p.read_bytes() for p in v1.rglob("*") if p.is_file() and ".lock" not in p.parts} == before
    finally:
        holder.kill()  # dies holding the folder: its lock must not outlive it
        holder.wait()
    assert records_cli(["migrate", str(v1)]) == 0
    assert validate_dataset(v1) == [] and not (v1 / ".migrate.json").exists() and not (v1 / ".lock").exists()


def test_two_migrations_at_once_leave_one_migrated_folder(v1):
    runs = [
        subprocess.Popen(
            [sys.executable, "-m", "usl.cli.records", "migrate", str(v1)], stderr=subprocess.PIPE, text=True
        )
        for _ in range(2)
    ]
    results = [(run.wait(), run.stderr.read()) for run in runs]
    assert sorted(code for code, _ in results) in ([0, 0], [0, 2]), results
    assert all("Traceback" not in err for _, err in results), results
    assert validate_dataset(v1) == [] and not (v1 / ".migrate.json").exists() and not (v1 / ".lock").exists()


ENTER_AND_LEAVE = """
import sys
from pathlib import Path
from usl.errors import UslError
from usl.records.claims import sole_writer
refused = 0
for _ in range(int(sys.argv[2])):
    try:
        with sole_writer(Path(sys.argv[1]), "usl-records migrate"):
            pass
    except UslError:
        refused += 1
print(refused)
"""


def test_a_writer_finishing_never_breaks_one_starting(tmp_path):
    # The finishing writer removes the lock folders it leaves empty; the starting one may have just
    # made them. Hundreds of rounds at once hit that window on every machine seen so far.
    rounds = 300
    runs = [
        subprocess.Popen(
            [sys.executable, "-c", ENTER_AND_LEAVE, str(tmp_path), str(rounds)],
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
        )
        for _ in range(2)
    ]
    results = [(run.wait(), *run.communicate()) for run in runs]
    assert [code for code, _, _ in results] == [0, 0], results
    assert all(0 <= int(out) < rounds for _, out, _ in results)
    assert list(tmp_path.iterdir()) == []
