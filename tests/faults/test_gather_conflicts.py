"""``usl-records gather`` on parts that disagree or lie: refused in one line, before anything is written."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from tests.faults.outputs import finished_files, one_line_error
from tests.faults.small_build import build
from usl.cli.records import main as records_main
from usl.records.schema import shard_file

SHARD = "val-00000"  # the shard the parts below disagree on


@pytest.fixture(scope="module")
def parts(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path]:
    """Two whole builds of one command, and a build of another seed (same shard plan)."""
    root = tmp_path_factory.mktemp("parts")
    for name, seed in (("a", 3), ("b", 3), ("other", 4)):
        assert build(root / name, seed=seed) == 0
    return root / "a", root / "b", root / "other"


def gather(*folders: Path, out: Path) -> int:
    return records_main(["gather", *map(str, folders), "--out", str(out)])


def transplant(source: Path, target: Path) -> None:
    """Give ``target`` the ``source`` build's copy of SHARD (files and record), keeping its build.json."""
    for table in ("frames", "objects"):
        file = shard_file(table, "val", 0)
        shutil.copyfile(source / file, target / file)
    shutil.copyfile(source / ".build" / f"{SHARD}.json", target / ".build" / f"{SHARD}.json")


def test_identical_copies_gather_to_the_same_dataset(parts, tmp_path, capsys):
    a, b, _ = parts
    assert gather(a, b, out=tmp_path / "out") == 0
    assert (
        finished_files(tmp_path / "out")[shard_file("frames", "val", 0)]
        == (a / shard_file("frames", "val", 0)).read_bytes()
    )


def test_differing_copies_of_a_shard_are_an_error_naming_both_parts(parts, tmp_path, capsys, fault_tally):
    a, b, other = parts
    b2 = tmp_path / "b2"
    shutil.copytree(b, b2)
    transplant(other, b2)
    out = tmp_path / "out"
    assert gather(a, b2, out=out) == 2
    fault_tally.tried += 1
    message = one_line_error(capsys.readouterr().err)
    assert f"{a} and {b2} hold different copies" in message and "val/0" in message
    assert not out.exists(), "parts are checked before anything is written"
    fault_tally.survived += 1

    assert gather(a, out=out) == 0  # the output then holds a's copy: b2's differs from it too
    kept = finished_files(out)
    assert gather(b2, out=out) == 2
    fault_tally.tried += 1
    assert f"{out} and {b2} hold different copies" in one_line_error(capsys.readouterr().err)
    assert finished_files(out) == kept
    fault_tally.survived += 1


def edit_record(part: Path, edit) -> None:
    path = part / ".build" / f"{SHARD}.json"
    path.write_text(json.dumps(edit(json.loads(path.read_text()))))


HOSTILE_RECORDS = {
    "shard file in the folder above": (
        lambda r: {**r, "frames": {**r["frames"], "file": "../../escape.parquet"}},
        "points outside the dataset folder",
    ),
    "absolute shard file": (lambda r: {**r, "frames": {**r["frames"], "file": "/etc/passwd"}}, "points outside"),
    "another shard's file": (
        lambda r: {**r, "frames": {**r["frames"], "file": shard_file("frames", "train", 0)}},
        "is not 'frames/val/frames-00000.parquet'",
    ),
    "record of another split": (lambda r: {**r, "split": "../../x"}, "records shard '../../x'/0, not val/0"),
    "record without files": (lambda r: {"split": "val"}, "not a shard record"),
    "record that is a list": (lambda r: [r], "not a shard record"),
}


@pytest.mark.parametrize("case", HOSTILE_RECORDS)
def test_a_part_record_cannot_lead_gather_outside_its_folders(case, parts, tmp_path, capsys, fault_tally):
    edit, expected = HOSTILE_RECORDS[case]
    part = tmp_path / "deep" / "er" / "part"
    shutil.copytree(parts[0], part)
    edit_record(part, edit)
    out = tmp_path / "deep" / "er" / "out"
    assert gather(part, out=out) == 2
    fault_tally.tried += 1
    assert expected in one_line_error(capsys.readouterr().err)
    assert not out.exists() and sorted(p.name for p in (tmp_path / "deep").rglob("*escape*")) == []
    fault_tally.survived += 1


def test_a_hostile_split_in_a_part_build_file_is_refused(parts, tmp_path, capsys):
    part = tmp_path / "part"
    shutil.copytree(parts[0], part)
    path = part / ".build" / "build.json"
    description = json.loads(path.read_text())
    description["shards"][0][0] = "../../x"
    path.write_text(json.dumps(description))
    assert gather(part, out=tmp_path / "out") == 2
    assert "split '../../x' holds a path separator" in one_line_error(capsys.readouterr().err)
    assert not (tmp_path / "out").exists() and not list(tmp_path.parent.glob("x-*"))
