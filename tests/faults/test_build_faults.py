"""A build whose disk fills up or turns read-only at any write: one line, nothing finished lost, a rerun finishes.

The build resumed here has one of three shards left (and its manifest); every write operation of
that run fails in turn, once with ENOSPC and once with EACCES, then the same command runs again
with room to spare and must give the bytes of an uninterrupted build. The real-disk tests do the
same on a tmpfs that is too small, or that is remounted read-only between two runs.
"""

from __future__ import annotations

import json
import shutil
from functools import partial
from pathlib import Path

import pytest

from tests.faults.outputs import FAULTS, bytes_lost, finished_files, one_line_error, temp_files
from tests.faults.small_build import build
from usl.records.build_state import IDENTITY_KEYS

BUILD_JSON = ".build/build.json"


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    """The finished files of an uninterrupted build, its --out written as OUT."""
    out = tmp_path_factory.mktemp("reference") / "ds"
    assert build(out) == 0
    return out_as_placeholder(finished_files(out), out)


def out_as_placeholder(files: dict[str, bytes], out: Path) -> dict[str, bytes]:
    """The files with their --out written as OUT: the manifest, card and build.json name it."""
    return {name: data.replace(str(out).encode(), b"OUT") for name, data in files.items()}


@pytest.fixture(scope="module")
def half_built(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two of the three shards finished (the first machine of two), no manifest yet."""
    out = tmp_path_factory.mktemp("half") / "ds"
    assert build(out, "--num-shards", "2", "--shard-index", "0") == 0
    return out


def same_dataset(files: dict[str, bytes], reference: dict[str, bytes]) -> bool:
    """Equal files; of build.json (which records the command that began the folder) its identity."""

    def comparable(found: dict[str, bytes]) -> dict[str, object]:
        described = json.loads(found[BUILD_JSON])
        return {**found, BUILD_JSON: {key: described[key] for key in IDENTITY_KEYS}}

    return comparable(files) == comparable(reference)


def survive(out: Path, fault: str, reference: dict[str, bytes], capsys, tally) -> None:
    """After a failed run (already done): what a rerun must find and finish."""
    message = one_line_error(capsys.readouterr().err)
    assert fault in message and "rerun the same command to resume" in message and str(out) in message
    after_fault = finished_files(out)
    assert build(out) == 0, capsys.readouterr().err
    final = finished_files(out)
    tally.bytes_lost += bytes_lost(after_fault, final)
    assert bytes_lost(after_fault, final) == 0
    assert same_dataset(out_as_placeholder(final, out), reference)
    assert temp_files(out) == []
    tally.survived += 1


@pytest.mark.parametrize(("code", "fault"), FAULTS)
def test_every_write_of_a_build_fails_cleanly(
    code, fault, half_built, reference, tmp_path, write_faults, fail_write, capsys, fault_tally
):
    out = tmp_path / "count"
    shutil.copytree(half_built, out)
    counting = write_faults()
    assert build(out) == 0
    sites = list(counting.sites)
    assert {"Parquet row group", "rename into place (manifest.json)", "rename into place (frames-N.parquet)"} <= set(
        sites
    )
    for k, site in enumerate(sites):
        out = tmp_path / f"fault-{k}"
        shutil.copytree(half_built, out)
        before = finished_files(out)
        fail_write(k, code, site, partial(build, out))
        assert bytes_lost(before, finished_files(out)) == 0, site
        survive(out, fault, reference, capsys, fault_tally)


def test_a_full_disk_stops_the_build_and_a_bigger_one_finishes_it(small_disk, reference, capsys, fault_tally):
    size = sum(len(data) for data in reference.values())
    disk = small_disk.mount(size // 2)
    out = disk / "ds"
    assert build(out) == 2
    fault_tally.tried += 1
    small_disk.remount(disk, f"size={4 * size + (1 << 20)}")
    survive(out, "no space left", reference, capsys, fault_tally)


def test_a_folder_that_turns_read_only_stops_the_build_and_a_rerun_finishes_it(
    small_disk, half_built, reference, capsys, fault_tally
):
    disk = small_disk.mount(1 << 24)
    out = disk / "ds"
    shutil.copytree(half_built, out)
    before = finished_files(out)
    small_disk.remount(disk, "ro")
    assert build(out) == 2
    fault_tally.tried += 1
    assert bytes_lost(before, finished_files(out)) == 0
    small_disk.remount(disk, "rw")
    survive(out, "read-only file system", reference, capsys, fault_tally)
