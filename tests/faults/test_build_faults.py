"""A build whose disk fills up or turns read-only at any write: one line, nothing finished lost, a rerun finishes.

The build resumed here has one of three shards left (and its manifest); every write operation of
that run fails in turn, once with ENOSPC and once with EACCES, then the same command runs again
with room to spare and must give the bytes of an uninterrupted build. The real-disk tests do the
same on a tmpfs that is too small, or that is remounted read-only between two runs.
"""

from __future__ import annotations

import errno
import shutil
from pathlib import Path

import pytest
from tests.faults.outputs import bytes_lost, finished_files, one_line_error, temp_files, without_creator

from tests.faults.small_build import build


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> dict[str, bytes]:
    out = tmp_path_factory.mktemp("reference") / "ds"
    assert build(out) == 0
    return finished_files(out)


@pytest.fixture(scope="module")
def half_built(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Two of the three shards finished (the first machine of two), no manifest yet."""
    out = tmp_path_factory.mktemp("half") / "ds"
    assert build(out, "--num-shards", "2", "--shard-index", "0") == 0
    return out


def assert_same_dataset(files: dict[str, bytes], reference: dict[str, bytes]) -> None:
    assert sorted(files) == sorted(reference)
    for name, data in reference.items():
        if name in ("manifest.json", ".build/build.json"):
            continue  # they name their --out; compared without it below
        assert files[name] == data, name
    assert without_creator(files["manifest.json"]) == without_creator(reference["manifest.json"])


def survive(out: Path, fault: str, reference: dict[str, bytes], capsys, tally) -> None:
    """After a failed run (already done): what a rerun must find and finish."""
    message = one_line_error(capsys.readouterr().err)
    assert fault in message and "rerun the same command to resume" in message and str(out) in message
    after_fault = finished_files(out)
    assert build(out) == 0, capsys.readouterr().err
    final = finished_files(out)
    tally.bytes_lost += bytes_lost(after_fault, final)
    assert bytes_lost(after_fault, final) == 0
    assert_same_dataset(final, reference)
    assert temp_files(out) == []
    tally.survived += 1


@pytest.mark.parametrize(("code", "fault"), [(errno.ENOSPC, "no space left"), (errno.EACCES, "permission denied")])
def test_every_write_of_a_build_fails_cleanly(
    code, fault, half_built, reference, tmp_path, write_faults, capsys, fault_tally
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
        plan = write_faults(k, code)
        assert build(out) == 2, f"write {k} ({site}) failed but the build went on"
        assert plan.fired
        write_faults()  # writes work again
        fault_tally.tried += 1
        fault_tally.sites.add(site)
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
