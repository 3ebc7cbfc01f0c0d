"""One training writes a run folder at a time, and a full disk there ends it in one line.

Two trainings started on one ``--out`` would otherwise both run to the end, leaving the config of
one beside the weights of the other. The main process holds the folder (``usl.records.output_folder``:
the holder's host and pid, taken over once that process is gone); the other ranks of a
distributed run write nothing there. Holding it also reaps what a killed training left: temp
files of checkpoints, ``metrics.csv`` and ``curves.png`` named after their writer.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from usl.records.output_folder import output_folder

from .checkpoint import CHECKPOINT_DIR
from .command import COMMAND
from .distributed import DistInfo


@contextmanager
def hold_run_folder(run_dir: Path, info: DistInfo) -> Iterator[None]:
    """Hold ``run_dir`` for this training while the block runs (main process only), and raise a
    full disk or refused write inside it as one line saying how to resume."""
    if not info.is_main:
        yield
        return
    kept, resume = "the checkpoints written so far are kept", f"continue with {COMMAND} --resume --out {run_dir}"
    with output_folder(run_dir, COMMAND, kept, resume, token_dirs=(run_dir / CHECKPOINT_DIR,)):
        yield
