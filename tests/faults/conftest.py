"""Fault injection for the whole suite: failing writes, small real disks, and a tally of the results.

``write_faults`` fails the n-th write operation a piece of code performs (every way usl writes:
opening a file for writing, writing to it, Parquet row groups, fsync, the atomic rename, hard
links, new folders) with a chosen errno, so a test can walk every write site of a build or a
training one after another. ``small_disk`` is a real tmpfs of a given size (root only; skipped
otherwise). Each test adds what it tried to ``fault_tally``; the totals are printed at the end of
the run: faults tried, faults survived (one-line error, nothing finished lost, a rerun completes),
bytes of finished output lost.
"""

from __future__ import annotations

import builtins
import errno
import io
import os
import pathlib
import re
import subprocess
import threading
import uuid
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
import pytest

from tests.faults.tally import TALLY, Tally
from usl.records.tempfiles import TMP_MARK

_WRITE_FLAGS = os.O_WRONLY | os.O_RDWR | os.O_CREAT | os.O_APPEND


@pytest.fixture
def fault_tally() -> Tally:
    return TALLY


def written(path: Any) -> str:
    """What kind of file a write is for: the file name with digits and writer tokens taken out."""
    name = Path(str(path)).name.split(TMP_MARK)[0].lstrip(".")
    return re.sub(r"[0-9a-f]{16}|\d+", "N", name)


@dataclass
class WriteFaults:
    """Counts write operations and fails the ``fail_at``-th (0-based) with ``errno_``."""

    fail_at: int | None = None
    errno_: int = errno.ENOSPC
    sites: list[str] = field(default_factory=list)  # the site of every operation seen, in order

    @property
    def fired(self) -> bool:
        return self.fail_at is not None and len(self.sites) > self.fail_at

    def hit(self, site: str, path: Any = None) -> None:
        if threading.current_thread() is not threading.main_thread():
            return  # background writers (TensorBoard's) interleave at random: only this thread's order is fixed
        self.sites.append(f"{site} ({written(path)})" if path is not None else site)
        if self.fail_at is not None and len(self.sites) - 1 == self.fail_at:
            raise OSError(self.errno_, os.strerror(self.errno_), *([str(path)] if path is not None else []))


@pytest.fixture
def write_faults(monkeypatch: pytest.MonkeyPatch) -> Callable[..., WriteFaults]:
    """``arm(fail_at=None, errno_=ENOSPC)``: patch every write operation to report to a fresh
    ``WriteFaults``, which fails the chosen one. Reading is never touched."""
    active: list[WriteFaults] = [WriteFaults()]

    def plan() -> WriteFaults:
        return active[0]

    real_open, real_os_open = builtins.open, os.open
    real_replace, real_link, real_fsync, real_mkdir = os.replace, os.link, os.fsync, os.mkdir
    real_write_table = pq.ParquetWriter.write_table

    class FailingFile(io.IOBase):
        """A file opened for writing whose writes report to the plan (a full disk fails there)."""

        def __init__(self, inner: Any, path: Any):
            self._inner, self._path = inner, path

        def write(self, data: Any) -> int:
            plan().hit("file write", self._path)
            return self._inner.write(data)

        def __getattr__(self, name: str) -> Any:
            return getattr(self._inner, name)

        def __enter__(self) -> FailingFile:
            return self

        def __exit__(self, *exc: Any) -> None:
            self._inner.close()

        def close(self) -> None:
            self._inner.close()

        def fileno(self) -> int:
            return self._inner.fileno()

        def flush(self) -> None:
            self._inner.flush()

    def failing_open(file: Any, mode: str = "r", *args: Any, **kwargs: Any) -> Any:
        if isinstance(file, int) or not any(c in mode for c in "wax+") or str(file).startswith("/dev/"):
            return real_open(file, mode, *args, **kwargs)
        plan().hit("open for writing", file)
        return FailingFile(real_open(file, mode, *args, **kwargs), file)

    def failing_os_open(path: Any, flags: int, *args: Any, **kwargs: Any) -> int:
        if flags & _WRITE_FLAGS and not str(path).startswith("/dev/"):  # /dev/null is no disk
            plan().hit("os.open for writing", path)
        return real_os_open(path, flags, *args, **kwargs)

    def failing_replace(src: Any, dst: Any, *args: Any, **kwargs: Any) -> None:
        plan().hit("rename into place", dst)
        real_replace(src, dst, *args, **kwargs)

    def failing_link(src: Any, dst: Any, *args: Any, **kwargs: Any) -> None:
        plan().hit("hard link", dst)
        real_link(src, dst, *args, **kwargs)

    def failing_fsync(fd: Any) -> None:
        plan().hit("fsync")
        real_fsync(fd)

    def failing_mkdir(path: Any, *args: Any, **kwargs: Any) -> None:
        if not os.path.isdir(path):
            plan().hit("new folder", path)
        real_mkdir(path, *args, **kwargs)

    def failing_write_table(self: Any, table: Any, *args: Any, **kwargs: Any) -> None:
        plan().hit("Parquet row group")
        real_write_table(self, table, *args, **kwargs)

    monkeypatch.setattr(builtins, "open", failing_open)
    monkeypatch.setattr(io, "open", failing_open)
    monkeypatch.setattr(os, "open", failing_os_open)
    monkeypatch.setattr(os, "replace", failing_replace)
    monkeypatch.setattr(os, "link", failing_link)
    monkeypatch.setattr(os, "fsync", failing_fsync)
    monkeypatch.setattr(os, "mkdir", failing_mkdir)
    if hasattr(pathlib, "_normal_accessor"):  # Python 3.10: Path.mkdir/replace call os's functions bound at import
        monkeypatch.setattr(pathlib._normal_accessor, "mkdir", failing_mkdir)
        monkeypatch.setattr(pathlib._normal_accessor, "replace", failing_replace)
    monkeypatch.setattr(pq.ParquetWriter, "write_table", failing_write_table)

    def arm(fail_at: int | None = None, errno_: int = errno.ENOSPC) -> WriteFaults:
        active[0] = WriteFaults(fail_at, errno_)
        return active[0]

    return arm


class SmallDisks:
    """Real tmpfs mounts of a chosen size (root only), all unmounted at teardown."""

    def __init__(self, parent: Path):
        self.parent, self.mounted = parent, []

    def mount(self, size: int) -> Path:
        target = self.parent / f"disk-{uuid.uuid4().hex[:6]}"
        target.mkdir()
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(target)], capture_output=True)
        if done.returncode != 0:
            pytest.skip(f"cannot mount a tmpfs here: {done.stderr.decode().strip()}")
        self.mounted.append(target)
        return target

    def remount(self, target: Path, options: str) -> None:
        """``size=<bytes>``, ``ro`` or ``rw``: the mounted disk changes under the files on it."""
        subprocess.run(["mount", "-o", f"remount,{options}", str(target)], check=True)


@pytest.fixture
def fail_write(write_faults: Callable[..., WriteFaults]) -> Callable[[int, int, str, Callable[[], int]], None]:
    """``fail_write(position, errno_, label, run)``: ``run()`` with that write failing must exit 2;
    writes work again afterwards, and the fault is tallied under ``label``."""

    def fail(position: int, errno_: int, label: str, run: Callable[[], int]) -> None:
        plan = write_faults(position, errno_)
        assert run() == 2, f"{label} failed but the command went on"
        assert plan.fired
        write_faults()
        TALLY.tried += 1
        TALLY.sites.add(label)

    return fail


@pytest.fixture
def small_disk(tmp_path: Path) -> Iterator[SmallDisks]:
    if os.geteuid() != 0:
        pytest.skip("mounting a tmpfs needs root")
    disks = SmallDisks(tmp_path)
    yield disks
    for target in disks.mounted:
        subprocess.run(["umount", "-l", str(target)], check=True)
