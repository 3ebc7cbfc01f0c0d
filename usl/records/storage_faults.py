"""A full disk or a refused write as one line that says what is kept and how to go on.

Every usl writer writes a temp file and renames it into place, so a write that fails for lack of
space or permission loses nothing finished; the temp file goes (or is reaped once its writer is
gone) and a rerun resumes. Without this module the user would learn that from a traceback deep in
pyarrow or ``torch.save`` (which hides the ENOSPC in a chained exception), if at all.
"""

from __future__ import annotations

import errno
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from usl.errors import UslError

SPACE_ERRNOS = {errno.ENOSPC: "no space left on the device", errno.EDQUOT: "disk quota exceeded"}
ACCESS_ERRNOS = {
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.EROFS: "read-only file system",
}
RERUN = "rerun the same command to resume"  # builds, gather, migrate: a rerun finds what is done


def storage_cause(exc: BaseException | None) -> OSError | None:
    """The full-disk or no-permission OSError behind ``exc``, also when another exception wraps it."""
    seen: set[int] = set()
    while exc is not None and id(exc) not in seen:
        seen.add(id(exc))
        if isinstance(exc, OSError) and (exc.errno in SPACE_ERRNOS or exc.errno in ACCESS_ERRNOS):
            return exc
        exc = exc.__cause__ or exc.__context__
    return None


def storage_message(cause: OSError, where: Path, kept: str, resume: str = RERUN) -> str:
    """``<where>: <what ran out> (errno N); <kept>: <what to do>``. A full disk is named by the folder
    being written (the file is often a temp file, or unknown to pyarrow); a refused write by its file."""
    if cause.errno in SPACE_ERRNOS:
        return f"{where}: {SPACE_ERRNOS[cause.errno]} (errno {cause.errno}); {kept}: free space and {resume}"
    path = cause.filename or where
    return f"{path}: cannot write, {ACCESS_ERRNOS[cause.errno]} (errno {cause.errno}); {kept}: fix that and {resume}"


@contextmanager
def storage_faults(where: Path, kept: str, resume: str = RERUN) -> Iterator[None]:
    """Raise a full disk or refused write inside the block as a one-line UslError.

    ``where`` is the folder being written, ``kept`` what survives the failure (``the shards
    finished so far are kept``), ``resume`` how to go on. Any other exception passes unchanged.
    """
    try:
        yield
    except UslError:
        raise
    except Exception as exc:
        cause = storage_cause(exc)
        if cause is None:
            raise
        raise UslError(storage_message(cause, Path(where), kept, resume)) from exc
