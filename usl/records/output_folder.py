"""Writing a folder as its one writer, with a full disk or refused write as one line.

The command lines that write a folder of results (``usl-train``'s run folder, ``usl-eval`` and
``usl-predict``'s ``--out``) all need the same two guards: another live process writing the same
folder is refused, naming its host and pid (``claims.sole_writer``), and a full disk or a folder
that turns read-only says what is kept and how to go on (``storage_faults``).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from .claims import sole_writer
from .storage_faults import RERUN, storage_faults


@contextmanager
def output_folder(
    folder: Path, command: str, kept: str, resume: str = RERUN, token_dirs: tuple[Path, ...] = ()
) -> Iterator[None]:
    """Hold ``folder`` for ``command`` while the block runs; ``kept`` and ``resume`` complete the
    one line a full disk becomes (``storage_faults``), ``token_dirs`` are sub-folders whose temp
    files a killed holder leaves (reaped by the next holder)."""
    with storage_faults(folder, kept, resume):
        with sole_writer(folder, command, token_dirs):
            yield
