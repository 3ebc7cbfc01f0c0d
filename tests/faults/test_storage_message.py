"""The one line a full disk or refused write becomes, also when a library hides the OSError."""

from __future__ import annotations

import errno
from pathlib import Path

import pytest

from usl.errors import UslError
from usl.records.storage_faults import storage_cause, storage_faults


def torch_save_like_failure() -> None:
    """What torch.save raises on a full disk: its own RuntimeError, the ENOSPC only in the chain."""
    try:
        raise OSError(errno.ENOSPC, "No space left on device")
    except OSError:
        # as torch raises it: chained implicitly, the OSError only in __context__
        raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 1024 vs 980")  # noqa: B904


def test_the_oserror_behind_a_wrapping_exception_is_found():
    with pytest.raises(RuntimeError) as caught:
        torch_save_like_failure()
    assert storage_cause(caught.value).errno == errno.ENOSPC
    assert storage_cause(RuntimeError("other")) is None
    assert storage_cause(FileNotFoundError(errno.ENOENT, "gone")) is None  # a bug, not a full disk


def test_a_full_disk_names_the_folder_and_how_to_resume():
    with pytest.raises(UslError) as caught:
        with storage_faults(Path("runs/a"), "the checkpoints written so far are kept", "resume with X"):
            torch_save_like_failure()
    assert str(caught.value) == (
        "runs/a: no space left on the device (errno 28); the checkpoints written so far are kept: "
        "free space and resume with X"
    )


def test_a_refused_write_names_the_file_and_other_errors_pass():
    with pytest.raises(UslError, match=r"^out/x.json: cannot write, read-only file system \(errno 30\); kept: fix"):
        with storage_faults(Path("out"), "kept"):
            raise OSError(errno.EROFS, "Read-only file system", "out/x.json")
    with pytest.raises(ValueError):
        with storage_faults(Path("out"), "kept"):
            raise ValueError("a bug stays a traceback")
